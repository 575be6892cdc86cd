"""Mechanisms to and from pylinkage (`pip install links-ray[pylinkage]`), and as a script.

A links-ray mechanism maps onto pylinkage's definition API one joint for one component: a fixed
joint is a `Ground`, joint 1 a `Crank` about joint 0, and each simple joint an `RRRDyad` on the
two joints that solve it (its solution path's parents), with the distances and the starting
point of the initial pose. The crank turns 2 pi / steps per step, counter-clockwise, as
links-ray's does, so pylinkage's `Linkage.step()` traces the same loci, shifted by one step:
pylinkage yields the pose after each turn of the crank, so its yield k is links-ray's step
k + 1 and its last one the starting pose. pylinkage keeps each dyad on the intersection nearest
its previous position, links-ray on the side it started on: the two agree while no dyad comes
within a crank step of its dead centre.

pylinkage is imported only by `to_pylinkage` and `from_pylinkage`; `pylinkage_script` writes
text and needs no pylinkage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from links_ray.engine.inputs import (
    DEFAULT_STEPS,
    InvalidMechanismError,
    as_int,
    as_positions,
    as_steps,
    check_positions,
)
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.engine.node_kinds import ACTUATED, FIXED, SIMPLE

if TYPE_CHECKING:
    import pylinkage

INSTALL_HINT = "pylinkage is not installed: pip install 'links-ray[pylinkage]'"


@dataclass(frozen=True)
class _Part:
    """One joint as a pylinkage component: "ground" (x, y), "crank" (radius, initial angle)
    or "dyad" (anchors a and b, distances to them, starting x and y)."""

    joint: int
    kind: str
    anchors: tuple[int, ...]
    values: tuple[float, ...]


def _parts(adjacency: ArrayLike, node_types: ArrayLike, positions: ArrayLike) -> list[_Part]:
    """The components that build the mechanism, in an order where anchors come first."""
    topology = analyze_topology(adjacency, node_types)
    pos = as_positions(positions, topology.n_joints)
    check_positions(topology.adjacency, pos)
    parts = [
        _Part(int(j), "ground", (), (float(pos[j, 0]), float(pos[j, 1])))
        for j in topology.fixed_joints
    ]
    dx, dy = pos[1] - pos[0]
    parts.append(_Part(1, "crank", (0,), (float(math.hypot(dx, dy)), float(math.atan2(dy, dx)))))
    for j, a, b in topology.order.tolist():
        r1 = float(math.hypot(*(pos[j] - pos[a])))
        r2 = float(math.hypot(*(pos[j] - pos[b])))
        parts.append(_Part(j, "dyad", (a, b), (r1, r2, float(pos[j, 0]), float(pos[j, 1]))))
    return parts


def _import_pylinkage() -> Any:
    try:
        import pylinkage
    except ImportError:
        raise ImportError(INSTALL_HINT) from None
    return pylinkage


def to_pylinkage(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    steps: int = DEFAULT_STEPS,
    name: str = "links-ray mechanism",
) -> pylinkage.Linkage:
    """The mechanism as a `pylinkage.Linkage`: its components in joint order, named "J0",
    "J1", ..., the crank turning 2 pi / `steps` per step (one turn in `steps` steps).

    Raises `InvalidMechanismError` (a `ValueError`) for a malformed mechanism and `ImportError`
    without pylinkage.
    """
    steps = as_steps(steps)
    parts = _parts(adjacency, node_types, positions)
    pl = _import_pylinkage()
    made: dict[int, Any] = {}
    for part in parts:
        label = f"J{part.joint}"
        if part.kind == "ground":
            made[part.joint] = pl.Ground(*part.values, name=label)
        elif part.kind == "crank":
            radius, angle = part.values
            made[part.joint] = pl.Crank(
                made[0], radius, angular_velocity=math.tau / steps, initial_angle=angle, name=label
            )
        else:
            a, b = (made[k].output if k == 1 else made[k] for k in part.anchors)
            r1, r2, x, y = part.values
            made[part.joint] = pl.RRRDyad(a, b, r1, r2, x=x, y=y, name=label)
    return pl.Linkage([made[j] for j in sorted(made)], name=name)


def from_pylinkage(linkage: pylinkage.Linkage) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(adjacency, node_types, positions) of a pylinkage linkage of `Ground`s, one `Crank`
    and `RRRDyad`s.

    The crank's anchor becomes joint 0 and the crank joint 1; the other components follow in
    the linkage's order. Each dyad is placed where pylinkage would assemble it: at the
    intersection of its two circles nearest its current coordinates. Raises `ValueError`
    naming the problem: another kind of component, not exactly one crank, an anchor outside
    the linkage, a dyad that cannot be assembled, or what links-ray refuses of the result.
    """
    pl = _import_pylinkage()
    components = list(linkage.components)
    for component in components:
        if type(component) not in (pl.Ground, pl.Crank, pl.RRRDyad):
            raise ValueError(
                f"component {component.name!r} is a {type(component).__name__}: links-ray "
                "mechanisms hold only Ground, Crank and RRRDyad components"
            )
    cranks = [c for c in components if isinstance(c, pl.Crank)]
    if len(cranks) != 1:
        raise ValueError(f"a links-ray mechanism has exactly one Crank, this has {len(cranks)}")
    crank = cranks[0]
    if not any(crank.anchor is c for c in components):
        raise ValueError(f"the crank's anchor {crank.anchor.name!r} is not in the linkage")
    if not isinstance(crank.anchor, pl.Ground):
        raise ValueError(f"the crank turns about {crank.anchor.name!r}, which is not a Ground")
    ordered = [
        crank.anchor,
        crank,
        *(c for c in components if c is not crank.anchor and c is not crank),
    ]
    index = {id(c): j for j, c in enumerate(ordered)}
    n = len(ordered)
    adjacency = np.zeros((n, n), dtype=np.int64)
    node_types = np.full(n, SIMPLE, dtype=np.int64)
    positions = np.full((n, 2), np.nan)
    adjacency[0, 1] = adjacency[1, 0] = 1
    node_types[1] = ACTUATED
    for j, component in enumerate(ordered):
        if isinstance(component, pl.Ground):
            node_types[j] = FIXED
            positions[j] = _coordinates(component)
        elif isinstance(component, pl.RRRDyad):
            for anchor in component.anchors:
                if id(anchor) not in index:
                    raise ValueError(
                        f"dyad {component.name!r} hangs on {anchor.name!r}, not in the linkage"
                    )
                k = index[id(anchor)]
                adjacency[j, k] = adjacency[k, j] = 1
    angle = math.atan2(crank.y - crank.anchor.y, crank.x - crank.anchor.x)
    positions[1] = positions[0] + crank.radius * np.array([math.cos(angle), math.sin(angle)])
    _assemble(pl, ordered, index, positions)
    topology = analyze_topology(adjacency, node_types)  # links-ray's own rules, by name
    check_positions(topology.adjacency, as_positions(positions, n))
    return adjacency, node_types, positions


def _coordinates(component: Any) -> tuple[float, float]:
    if component.x is None or component.y is None:
        raise ValueError(f"component {component.name!r} has no position")
    return float(component.x), float(component.y)


def _assemble(pl: Any, ordered: list, index: dict[int, int], positions: np.ndarray) -> None:
    """Place each dyad once both its anchors are placed, at its circles' intersection nearest
    its current coordinates (their midpoint if it has none), as pylinkage does."""
    waiting = [(j, c) for j, c in enumerate(ordered) if isinstance(c, pl.RRRDyad)]
    while waiting:
        ready = [
            (j, c)
            for j, c in waiting
            if all(not np.isnan(positions[index[id(a)], 0]) for a in c.anchors)
        ]
        if not ready:
            names = ", ".join(repr(c.name) for _, c in waiting)
            raise InvalidMechanismError(f"dyads {names} never have both anchors placed")
        for j, dyad in ready:
            (ax, ay), (bx, by) = (positions[index[id(a)]] for a in dyad.anchors)
            found = pl.circle_intersect(ax, ay, dyad.distance1, bx, by, dyad.distance2)
            if found[0] not in (1, 2):
                raise ValueError(
                    f"dyad {dyad.name!r} cannot be assembled: its circles do not meet in one "
                    "or two points"
                )
            hint = (
                ((ax + bx) / 2, (ay + by) / 2)
                if dyad.x is None or dyad.y is None
                else (dyad.x, dyad.y)
            )
            options = np.array(found[1:5], dtype=np.float64).reshape(2, 2)[: found[0]]
            nearest = np.argmin(np.hypot(*(options - np.asarray(hint, dtype=np.float64)).T))
            positions[j] = options[nearest]
        placed = {j for j, _ in ready}
        waiting = [(j, c) for j, c in waiting if j not in placed]


def pylinkage_script(
    adjacency: ArrayLike,
    node_types: ArrayLike,
    positions: ArrayLike,
    steps: int = DEFAULT_STEPS,
    title: str = "a links-ray mechanism",
    decimals: int | None = None,
) -> str:
    """A Python script that builds the mechanism with pylinkage, as `to_pylinkage` does, and
    prints each joint's position at every step when run. Numbers are written exactly, or
    rounded to `decimals` places."""
    steps = as_steps(steps)
    parts = _parts(adjacency, node_types, positions)
    if decimals is not None:
        places = as_int("decimals", decimals, 0, 17)
        # Lengths and coordinates, not the crank's angle: its error grows with the radius.
        parts = [
            _Part(
                p.joint,
                p.kind,
                p.anchors,
                tuple(
                    v if (p.kind, k) == ("crank", 1) else round(v, places) + 0.0
                    for k, v in enumerate(p.values)
                ),
            )
            for p in parts
        ]
    n = len(parts)
    lines = [
        f'"""{title} as a pylinkage linkage: {n} joints, J0 to J{n - 1}.',
        "",
        "J0 is the crank's pivot and J1 its tip; the crank turns counter-clockwise, one turn",
        f"in {steps} steps. Made by links-ray (`links export --format pylinkage`).",
        '"""',
        "",
        "import math",
        "",
        "import pylinkage as pl",
        "",
    ]
    for part in parts:
        label = f"J{part.joint}"
        if part.kind == "ground":
            x, y = part.values
            lines.append(f'{label.lower()} = pl.Ground({x!r}, {y!r}, name="{label}")')
        elif part.kind == "crank":
            radius, angle = part.values
            lines.append(
                f"j1 = pl.Crank(j0, radius={radius!r}, angular_velocity=math.tau / {steps}, "
                f'initial_angle={angle!r}, name="J1")'
            )
        else:
            a, b = (f"j{k}.output" if k == 1 else f"j{k}" for k in part.anchors)
            r1, r2, x, y = part.values
            lines.append(
                f"{label.lower()} = pl.RRRDyad({a}, {b}, distance1={r1!r}, distance2={r2!r}, "
                f'x={x!r}, y={y!r}, name="{label}")'
            )
    joints = ", ".join(f"j{j}" for j in range(n))
    lines += [
        f'linkage = pl.Linkage([{joints}], name="{title}")',
        "",
        'if __name__ == "__main__":',
        "    for step, pose in enumerate(linkage.step(), 1):",
        '        print(step, " ".join(f"{x:.6f},{y:.6f}" for x, y in pose))',
    ]
    return "\n".join(lines) + "\n"
