"""pylinkage interop (interop/pylinkage.py): a mechanism made a pylinkage linkage traces the
loci links-ray simulates, comes back as the same mechanism, and its script builds it too.

pylinkage yields the pose after each crank step, so its yield k is links-ray's step k + 1;
the comparison rolls its loci by one step, nothing else.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.engine.fabrication.drawings import fabrication
from links_ray.engine.inputs import DEFAULT_MIN_TRANSMISSION_DEG
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.engine.kinematics.transmission import mechanism_transmission_deg
from links_ray.interop.pylinkage import from_pylinkage, pylinkage_script, to_pylinkage
from tests.support.fourbars import stretched_four_bar
from tests.support.needs import need_module
from tests.support.serving import FOUR_BAR

pl = need_module("pylinkage", "pip install pylinkage (the test extra)")


def loci(linkage: Any, steps: int) -> np.ndarray:
    """pylinkage's joint loci over one crank turn as links-ray's (n, steps, 2): step 0 first."""
    poses = np.array(list(linkage.step(iterations=steps)), dtype=np.float64)
    return np.roll(poses, 1, axis=0).transpose(1, 0, 2)


def least_transmission(mech: dict[str, Any], trajectories: np.ndarray) -> float:
    order = analyze_topology(mech["adjacency"], mech["node_types"]).order
    return float(mechanism_transmission_deg(order, trajectories[None])[0])


def margined_mechanisms(count: int) -> list[dict[str, Any]]:
    """Random dataset mechanisms whose every dyad keeps DEFAULT_MIN_TRANSMISSION_DEG from its dead
    centre: pylinkage's nearest-point branch is then links-ray's frozen one."""
    found = []
    seed = 0
    while len(found) < count:
        adjacency, node_types = links_ray.random_topology(seed)
        for positions in links_ray.sample_positions(adjacency, node_types, count=5, seed=seed):
            mech = {"adjacency": adjacency, "node_types": node_types, "positions": positions}
            if least_transmission(mech, links_ray.simulate(**mech)) >= DEFAULT_MIN_TRANSMISSION_DEG:
                found.append(mech)
                break
        seed += 1
    return found


def closed_form_four_bar(mech: dict[str, Any], steps: int) -> np.ndarray:
    """Joint 3 of a tests/support/fourbars.py four-bar at every step, by the law of cosines."""
    pos = np.asarray(mech["positions"], dtype=np.float64)
    r1, r2 = math.dist(pos[3], pos[1]), math.dist(pos[3], pos[2])
    start = math.atan2(*(pos[1] - pos[0])[::-1])
    out = np.empty((steps, 2))
    (ux, uy), (vx, vy) = pos[2] - pos[1], pos[3] - pos[1]
    side = math.copysign(1.0, ux * vy - uy * vx)
    for t in range(steps):
        angle = start + 2 * math.pi * t / steps
        tip = pos[0] + math.dist(pos[0], pos[1]) * np.array([math.cos(angle), math.sin(angle)])
        gap = pos[2] - tip
        d = math.hypot(*gap)
        along = (d * d + r1 * r1 - r2 * r2) / (2 * d)
        normal = np.array([-gap[1], gap[0]]) / d
        out[t] = tip + along * gap / d + side * math.sqrt(r1 * r1 - along * along) * normal
    return out


@pytest.mark.parametrize("steps", [200, 360, 50])
def test_four_bars_trace_the_closed_form_and_links_ray(steps: int) -> None:
    for mech in (FOUR_BAR, stretched_four_bar(40, steps, slack=0.02)):
        truth = closed_form_four_bar(mech, steps)
        ours = links_ray.simulate(**mech, steps=steps)
        theirs = loci(to_pylinkage(**mech, steps=steps), steps)
        np.testing.assert_allclose(ours[3], truth, atol=1e-12, rtol=0)
        np.testing.assert_allclose(theirs, ours, atol=1e-9, rtol=0)


def test_random_dataset_mechanisms_trace_as_links_ray() -> None:
    for mech in margined_mechanisms(6):
        ours = links_ray.simulate(**mech)
        linkage = to_pylinkage(**mech)
        assert linkage.get_rotation_period() == 200
        assert [c.name for c in linkage.components] == [
            f"J{j}" for j in range(len(mech["node_types"]))
        ]
        np.testing.assert_allclose(loci(linkage, 200), ours, atol=1e-9, rtol=0)


def test_round_trip_gives_the_same_mechanism() -> None:
    for mech in [FOUR_BAR, *margined_mechanisms(4)]:
        adjacency, node_types, positions = from_pylinkage(to_pylinkage(**mech))
        np.testing.assert_array_equal(adjacency, mech["adjacency"])
        np.testing.assert_array_equal(node_types, mech["node_types"])
        np.testing.assert_allclose(positions, mech["positions"], atol=1e-12, rtol=0)
        # After a turn of pylinkage's crank the linkage is back where it started.
        linkage = to_pylinkage(**mech)
        list(linkage.step())
        _, _, again = from_pylinkage(linkage)
        np.testing.assert_allclose(again, mech["positions"], atol=1e-9, rtol=0)


def test_a_linkage_built_in_pylinkage_comes_in() -> None:
    # Built the pylinkage way: the dyad assembles itself, no starting point given; the
    # crank's anchor is not the first component.
    o2 = pl.Ground(3.0, 0.0, name="O2")
    o1 = pl.Ground(0.0, 0.0, name="O1")
    crank = pl.Crank(o1, radius=1.0, angular_velocity=math.tau / 100, initial_angle=0.5)
    rocker = pl.RRRDyad(crank.output, o2, distance1=3.0, distance2=2.0, name="rocker")
    linkage = pl.Linkage([o2, o1, crank, rocker])
    adjacency, node_types, positions = from_pylinkage(linkage)
    assert node_types.tolist() == [0, 2, 0, 1]  # anchor, crank, then the linkage's order
    assert adjacency.tolist() == [[0, 1, 0, 0], [1, 0, 0, 1], [0, 0, 0, 1], [0, 1, 1, 0]]
    np.testing.assert_allclose(positions[:3], [[0, 0], [math.cos(0.5), math.sin(0.5)], [3, 0]])
    np.testing.assert_allclose(positions[3], [rocker.x, rocker.y], atol=1e-12)
    ours = links_ray.simulate(adjacency, node_types, positions, steps=100)
    # pylinkage's loci in its components' order: O2, O1, crank, rocker.
    np.testing.assert_allclose(loci(linkage, 100)[[1, 2, 0, 3]], ours, atol=1e-9, rtol=0)


def test_what_links_ray_cannot_hold_is_refused() -> None:
    o1, o2 = pl.Ground(0.0, 0.0, name="O1"), pl.Ground(3.0, 0.0, name="O2")
    crank = pl.Crank(o1, radius=1.0)
    with pytest.raises(ValueError, match="exactly one Crank, this has 0"):
        from_pylinkage(pl.Linkage([o1, o2]))
    slider = pl.LinearActuator(o2, angle=0.0, stroke=1.0, name="slider")
    with pytest.raises(ValueError, match="'slider' is a LinearActuator"):
        from_pylinkage(pl.Linkage([o1, crank, o2, slider]))
    far = pl.RRRDyad(crank.output, o2, distance1=0.5, distance2=0.5, x=1.0, y=1.0, name="far")
    with pytest.raises(ValueError, match="'far' cannot be assembled"):
        from_pylinkage(pl.Linkage([o1, crank, o2, far]))
    outside = pl.RRRDyad(crank.output, o2, distance1=3.0, distance2=2.0, name="hangs")
    with pytest.raises(ValueError, match="'hangs' hangs on 'O2', not in the linkage"):
        from_pylinkage(pl.Linkage([o1, crank, outside]))
    rocker = pl.RRRDyad(crank.output, o2, distance1=3.0, distance2=2.0, name="rocker")
    on_rocker = pl.Crank(rocker, radius=0.5, name="second")
    with pytest.raises(ValueError, match="exactly one Crank, this has 2"):
        from_pylinkage(pl.Linkage([o1, crank, o2, rocker, on_rocker]))
    alone = pl.Crank(rocker, radius=0.5, name="alone")
    with pytest.raises(ValueError, match="turns about 'rocker', which is not a Ground"):
        from_pylinkage(pl.Linkage([rocker, alone, o2]))
    # What links-ray itself refuses, in its own words.
    still = pl.Crank(o1, radius=0.0, name="still")
    with pytest.raises(ValueError, match="the crank has zero length"):
        from_pylinkage(pl.Linkage([o1, still, o2]))
    with pytest.raises(ValueError, match="no crank"):
        to_pylinkage(**{**FOUR_BAR, "adjacency": np.zeros((4, 4), dtype=int)})


def test_the_script_builds_the_mechanism_in_millimetres() -> None:
    mech = margined_mechanisms(1)[0]
    drawing = fabrication(**mech, crank_mm=20.0)
    script = pylinkage_script(mech["adjacency"], mech["node_types"], drawing.joints_mm)
    scope: dict[str, Any] = {"__name__": "links_export"}  # not "__main__": nothing printed
    exec(compile(script, "mechanism.py", "exec"), scope)
    linkage = scope["linkage"]
    adjacency, node_types, positions = from_pylinkage(linkage)
    np.testing.assert_array_equal(adjacency, mech["adjacency"])
    np.testing.assert_array_equal(node_types, mech["node_types"])
    np.testing.assert_allclose(positions, drawing.joints_mm, atol=1e-9, rtol=0)
    assert math.dist(positions[0], positions[1]) == pytest.approx(20.0, abs=1e-12)
    ours = links_ray.simulate(**mech)
    pos = np.asarray(mech["positions"])
    expected = (ours - pos[0]) * drawing.scale
    np.testing.assert_allclose(loci(linkage, 200), expected, atol=1e-9, rtol=0)
