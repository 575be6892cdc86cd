"""Which bars of a mechanism come within the clearance over a crank turn
(engine/fabrication/collisions.py).

Truth is a brute force written here: every pair's exact segment distance at 20,000 crank steps, its
own formula (the lines' crossing parameters) compiled apart from the engine's. Hand- built grazes
put a pair's closest approach midway between two of the check's steps, in closed form, where the
check's own sampled steps miss it; random valid mechanisms (engine/kinematics/sampling.py) check
every pair, and thresholds set right at a pair's graze.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.engine.fabrication.collisions import (
    Collisions,
    _relative_speeds,
    _velocities,
    find_collisions,
)
from links_ray.engine.fabrication.limits import DEFAULT_COLLISION_STEPS, MAX_LAYERED_JOINTS
from links_ray.engine.inputs import InvalidMechanismError
from links_ray.engine.kinematics.mechanism import LockingError, analyze_topology
from links_ray.engine.kinematics.solver import _dyad_geometry, topology_cache
from links_ray.engine.kinematics.topology import random_topology
from links_ray.engine.kinematics.transmission import joint_transmission_deg
from links_ray.engine.node_kinds import FIXED
from tests.support.bars import brute_force, pairs_of
from tests.support.serving import LOCKING_FOUR_BAR

#: The brute force's crank steps.
FINE_STEPS = 20_000
STEPS = DEFAULT_COLLISION_STEPS
#: The crank: its centre, tip and radius, as the dataset's.
CENTRE, R = np.array([0.5, 0.5]), 0.05


# -- mechanisms ---------------------------------------------------------------------------------


def random_mechanism(seed: int, joints: int) -> dict[str, Any]:
    adjacency, node_types = random_topology(seed, joints)
    positions = links_ray.sample_positions(adjacency, node_types, count=1, seed=seed)[0]
    return {"adjacency": adjacency, "node_types": node_types, "positions": positions}


def crank_and_stand(graze: float, steps: int = STEPS) -> dict[str, Any]:
    """The crank (joints 0, 1) and a still stand beside it: fixed joints 2 and 3, joint 4 on
    both (links 2-4, 3-4). Pin 2 sits `graze` outside the crank's circle, and link 2-4 runs
    square to the crank's reach there, so both are closest to the crank, `graze` away, when
    it points at joint 2: midway between steps 37 and 38 of `steps`."""
    away = 2 * np.pi * 37.5 / steps
    radial = np.array([np.cos(away), np.sin(away)])
    across = np.array([-radial[1], radial[0]])
    pin = CENTRE + (R + graze) * radial
    positions = np.array(
        [
            CENTRE,
            CENTRE + np.array([R, 0.0]),
            pin,
            pin + 0.2 * radial - 0.1 * across,
            pin + 0.15 * across,
        ]
    )
    adjacency = np.zeros((5, 5), dtype=int)
    for i, j in [(0, 1), (2, 4), (3, 4)]:
        adjacency[i, j] = adjacency[j, i] = 1
    return {"adjacency": adjacency, "node_types": [0, 2, 0, 0, 1], "positions": positions}


def link_index(collisions: Collisions, i: int, j: int) -> int:
    return int(np.flatnonzero((collisions.links == [i, j]).all(axis=1))[0])


def sampled_least(mechanism: dict[str, Any], pair: tuple[int, int, int, int]) -> float:
    """The pair's least distance at the check's own steps: what sampling alone would see."""
    traj = links_ray.simulate(**mechanism, steps=STEPS)
    return float(brute_force(traj, np.array([pair]))[0][0])


# -- grazes between two steps -------------------------------------------------------------------

GRAZE = 0.01
#: How far a threshold sits from the graze: far below the gap sampling leaves at 360 steps.
HAIR = 1e-7


@pytest.mark.parametrize("side", [+1, -1])
def test_a_pin_grazed_midway_between_two_steps(side: int) -> None:
    """The crank passes pin 2 at GRAZE midway between two steps. A threshold a hair above
    conflicts, though every step misses it; a hair below is proven clear."""
    stand = crank_and_stand(GRAZE)
    assert sampled_least(stand, (0, 1, 2, 2)) > GRAZE + 1e-6  # the steps miss the graze
    threshold = GRAZE + side * HAIR
    pin, clearance = 0.004, 0.001
    width = 2 * (threshold - clearance) - pin
    found = find_collisions(**stand, bar_width=width, clearance=clearance, pin_diameter=pin)
    assert found.pin_threshold == pytest.approx(threshold, abs=1e-15)
    crank = link_index(found, 0, 1)
    assert found.pin_conflicts[crank, 2] == (side > 0)
    assert not found.pin_unresolved[crank, 2]
    # Found at the graze, to within a hair; a pair proven clear keeps its threshold.
    assert found.pin_distance[crank, 2] == pytest.approx(GRAZE, abs=HAIR if side > 0 else 1e-3)
    assert found.pin_distance[crank, 2] >= GRAZE - 1e-15


@pytest.mark.parametrize("side", [+1, -1])
def test_two_links_grazing_midway_between_two_steps(side: int) -> None:
    """Link 2-4 lies square to the crank's reach, GRAZE outside its circle: the crank's body
    grazes it midway between two steps."""
    stand = crank_and_stand(GRAZE)
    assert sampled_least(stand, (0, 1, 2, 4)) > GRAZE + 1e-6
    threshold = GRAZE + side * HAIR
    found = find_collisions(
        **stand, bar_width=threshold - 0.001, clearance=0.001, pin_diameter=0.001
    )
    crank, bar = link_index(found, 0, 1), link_index(found, 2, 4)
    assert found.link_conflicts[crank, bar] == found.link_conflicts[bar, crank] == (side > 0)
    assert not found.link_unresolved[crank, bar]


def test_a_coarse_check_misses_what_the_check_between_steps_catches() -> None:
    """At 12 steps the graze sits 15 degrees from the nearest step; still caught."""
    stand = crank_and_stand(GRAZE, steps=12)
    found = find_collisions(
        **stand, bar_width=GRAZE, clearance=HAIR, pin_diameter=GRAZE / 2, steps=12
    )
    crank, bar = link_index(found, 0, 1), link_index(found, 2, 4)
    at_steps = brute_force(links_ray.simulate(**stand, steps=12), np.array([[0, 1, 2, 4]]))[0]
    assert at_steps[0] > 1.15 * GRAZE  # 17% outside at every step
    assert found.link_conflicts[crank, bar] and not found.link_unresolved[crank, bar]


# -- the bounds the proof rests on --------------------------------------------------------------


@pytest.mark.parametrize("seed", range(6))
def test_the_motion_bounds_hold_between_steps(seed: int) -> None:
    """Over each interval of a 120-step turn, every two joints' relative speed and relative
    acceleration, measured by differences at 100 times the steps, stay within the bounds
    found from the interval's two end poses; the velocities solved at a pose match central
    differences."""
    mechanism = random_mechanism(seed, 8 + seed)
    topology = topology_cache.simulator(mechanism["adjacency"], mechanism["node_types"]).topology
    pos, order = mechanism["positions"], topology.order
    n = len(pos)
    geometry = np.empty((len(order), 3))
    _dyad_geometry(order, pos, geometry)
    fixed = topology.node_types == FIXED
    a, b = order[:, 1], order[:, 2]
    fixed_distance = (topology.adjacency[a, b] != 0) | (fixed[a] & fixed[b])
    steps, finer = 120, 100
    fine_step = 2 * np.pi / (steps * finer)
    traj = links_ray.simulate(**mechanism, steps=steps * finer)
    # Every two joints' offset p_x - p_y, (n, n, steps * finer, 2).
    offsets = traj[:, None] - traj[None, :]
    following = np.roll(offsets, -1, axis=2)
    chords = np.linalg.norm(following - offsets, axis=3) / fine_step
    bends = np.linalg.norm(following - 2 * offsets + np.roll(offsets, 1, axis=2), axis=3)
    bends /= fine_step**2
    crank = float(np.hypot(*(pos[1] - pos[0])))
    relative, accel = np.empty((n, n)), np.empty((n, n))
    v_start, v_end = np.empty((n, 2)), np.empty((n, 2))
    finite = 0
    for t in range(steps):
        first, last = t * finer, ((t + 1) * finer) % (steps * finer)
        start, end = np.ascontiguousarray(traj[:, first]), np.ascontiguousarray(traj[:, last])
        _velocities(order, start, v_start)
        _velocities(order, end, v_end)
        central = (traj[:, first + 1] - traj[:, first - 1]) / (2 * fine_step)
        assert np.abs(v_start - central).max() <= 1e-4 * np.abs(central).max()
        _relative_speeds(
            order, geometry, fixed_distance, topology.fixed_joints, crank, start, end,
            v_start, v_end, 2 * np.pi / steps, relative, accel,
        )  # fmt: skip
        speeds = chords[:, :, first : first + finer].max(axis=2)
        assert np.all(speeds <= relative * (1 + 1e-9) + 1e-12), t
        bent = bends[:, :, first + 1 : first + finer].max(axis=2)
        assert np.all(bent <= accel * (1 + 1e-6) + 1e-9), t
        finite += np.isfinite(relative).all()
    assert finite > steps // 2


# -- every pair of random mechanisms, against the brute force -----------------------------------

#: (bar width, clearance, pin diameter) in the dataset's units, its crank 0.05 long.
SIZES = [(0.01, 0.0025, 0.005), (0.03, 0.005, 0.012)]


def entries(
    link_matrix: np.ndarray, pin_matrix: np.ndarray, which: np.ndarray, is_pin: np.ndarray
) -> np.ndarray:
    """Each pair's entry: of `pin_matrix` (link, joint) for a pin, else of `link_matrix`."""
    out = np.empty(len(which), dtype=link_matrix.dtype)
    out[is_pin] = pin_matrix[which[is_pin, 0], which[is_pin, 1]]
    out[~is_pin] = link_matrix[which[~is_pin, 0], which[~is_pin, 1]]
    return out


@pytest.fixture(scope="module")
def corpus() -> list[dict[str, Any]]:
    """100 random valid mechanisms of 8 to 12 joints, each with its pairs and their brute
    force at FINE_STEPS."""
    mechanisms = []
    for seed in range(100):
        mechanism = random_mechanism(1000 + seed, 8 + seed % 5)
        links, pairs, which, is_pin = pairs_of(np.asarray(mechanism["adjacency"]))
        trajectories = links_ray.simulate(**mechanism, steps=FINE_STEPS)
        least, dip = brute_force(trajectories, pairs)
        order = analyze_topology(mechanism["adjacency"], mechanism["node_types"]).order
        mechanisms.append(
            {
                "mechanism": mechanism,
                "links": links,
                "pairs": pairs,
                "which": which,
                "is_pin": is_pin,
                "least": least,
                "dip": dip,
                "least_deg": float(joint_transmission_deg(order, trajectories[None]).min()),
            }
        )
    return mechanisms


def test_every_pair_agrees_with_the_brute_force(corpus: list[dict[str, Any]]) -> None:
    """A pair the brute force finds within is a conflict; a conflict the brute force does not
    find is a graze finer than its steps, within a step's motion of the threshold, or a pair
    left undecided: only near a dead centre, where the joints' speeds outrun the subdivision's
    budget, and then counted as a conflict."""
    checked = agreed = finer = undecided = 0
    for entry in corpus:
        which, is_pin, least, dip = entry["which"], entry["is_pin"], entry["least"], entry["dip"]
        for width, clearance, pin in SIZES:
            found = find_collisions(
                **entry["mechanism"], bar_width=width, clearance=clearance, pin_diameter=pin
            )
            assert np.array_equal(found.links, entry["links"])
            unresolved = entries(found.link_unresolved, found.pin_unresolved, which, is_pin)
            if unresolved.any():
                assert entry["least_deg"] < 1.0, "pairs left undecided away from a dead centre"
            thresholds = np.where(is_pin, found.pin_threshold, found.link_threshold)
            within = least < thresholds
            conflicts = entries(found.link_conflicts, found.pin_conflicts, which, is_pin)
            distances = entries(found.link_distance, found.pin_distance, which, is_pin)
            assert np.all(conflicts[within]), "a pair within at a pose was reported clear"
            assert np.all(conflicts[unresolved])
            extra = conflicts & ~within & ~unresolved
            undecided += int(np.sum(unresolved & ~within))
            assert np.all(least[extra] - thresholds[extra] <= dip[extra])
            # The check's distances are at real poses: no less than the least between steps.
            assert np.all(distances >= least - dip - 1e-12)
            assert np.all(distances[~conflicts] >= thresholds[~conflicts])
            checked += len(which)
            agreed += int(np.sum(conflicts == within))
            finer += int(extra.sum())
    print(
        f"{checked} pairs: {agreed} agree, {finer} grazes finer than {FINE_STEPS} steps, "
        f"{undecided} undecided near a dead centre (counted as conflicts)"
    )
    assert agreed + finer + undecided == checked and finer <= checked // 1000
    assert undecided <= checked // 20


def test_thresholds_at_a_pairs_graze(corpus: list[dict[str, Any]]) -> None:
    """For pairs whose closest approach falls between the check's steps, a threshold just
    above the brute force's least conflicts, and one a step's motion below it is clear."""
    caught = 0
    for entry in corpus[:20]:
        mechanism, pairs, which, is_pin = (
            entry[k] for k in ("mechanism", "pairs", "which", "is_pin")
        )
        least, dip = entry["least"], entry["dip"]
        coarse, _ = brute_force(links_ray.simulate(**mechanism, steps=STEPS), pairs)
        between = np.flatnonzero((coarse - least > 1e-5) & (least > 1e-3))
        for i in between[:: max(1, len(between) // 2)][:2]:
            for threshold, conflict in ((least[i] + 1e-9, True), (least[i] - 2 * dip[i], False)):
                # Thresholds of the pair's kind, with no clearance and pins half the bars.
                width = threshold if not is_pin[i] else threshold / 0.75
                found = find_collisions(
                    **mechanism, bar_width=width, clearance=0.0, pin_diameter=width / 2
                )
                first, second = which[i]
                matrix = found.pin_conflicts if is_pin[i] else found.link_conflicts
                assert matrix[first, second] == conflict, (pairs[i], threshold, least[i])
                assert (
                    conflict
                    or not (found.pin_unresolved if is_pin[i] else found.link_unresolved)[
                        first, second
                    ]
                )
                caught += conflict
    print(f"{caught} grazes between the check's steps caught")
    assert caught >= 20


# -- the matrices' form --------------------------------------------------------------------------


def test_links_sharing_a_joint_conflict_at_distance_zero() -> None:
    mechanism = random_mechanism(7, 10)
    found = find_collisions(**mechanism, bar_width=0.001, clearance=0.0, pin_diameter=0.0005)
    links, n = found.links, len(mechanism["positions"])
    shared = (links[:, None, :, None] == links[None, :, None, :]).any(axis=(2, 3))
    np.fill_diagonal(shared, False)
    assert np.array_equal(found.link_conflicts, found.link_conflicts.T)
    assert np.array_equal(found.link_distance, found.link_distance.T)
    assert np.all(found.link_conflicts[shared]) and not np.diag(found.link_conflicts).any()
    assert np.all(found.link_distance[shared] == 0.0)
    own = np.zeros((len(links), n), dtype=bool)
    own[np.arange(len(links)), links[:, 0]] = own[np.arange(len(links)), links[:, 1]] = True
    assert not found.pin_conflicts[own].any() and np.all(found.pin_distance[own] == 0.0)
    assert found.steps == STEPS and found.splits >= 0


# -- refused input -----------------------------------------------------------------------------

FOUR_BAR = crank_and_stand(GRAZE)
SIZE = {"bar_width": 0.01, "clearance": 0.001, "pin_diameter": 0.004}


@pytest.mark.parametrize(
    ("change", "error", "message"),
    [
        ({"bar_width": -1.0}, ValueError, "bar_width must be more than 0"),
        ({"bar_width": float("nan")}, ValueError, "bar_width must be more than 0"),
        ({"bar_width": "wide"}, ValueError, "bar_width must be a length"),
        ({"clearance": -0.1}, ValueError, "clearance must be from 0"),
        ({"clearance": float("nan")}, ValueError, "clearance must be from 0"),
        ({"pin_diameter": 0.0}, ValueError, "pin_diameter must be more than 0"),
        ({"pin_diameter": 0.01}, ValueError, "pin_diameter must be less than bar_width"),
        ({"positions": np.zeros((4, 2))}, InvalidMechanismError, "positions must have shape"),
        ({"positions": np.full((5, 2), np.nan)}, InvalidMechanismError, "NaN or infinite"),
        ({"adjacency": np.ones((5, 5))}, InvalidMechanismError, "self-link"),
        ({"steps": 0}, InvalidMechanismError, "steps must be from 1"),
    ],
)
def test_bad_input_is_refused_by_name(
    change: dict[str, Any], error: type[Exception], message: str
) -> None:
    with pytest.raises(error, match=message):
        find_collisions(**{**FOUR_BAR, **SIZE, **change})


def test_a_locking_mechanism_is_refused() -> None:
    with pytest.raises(LockingError, match="mechanism locks at step"):
        find_collisions(**LOCKING_FOUR_BAR, **SIZE)


def test_a_mechanism_past_the_joint_limit_is_refused() -> None:
    adjacency, node_types = random_topology(0, MAX_LAYERED_JOINTS + 1)
    positions = np.random.default_rng(0).random((MAX_LAYERED_JOINTS + 1, 2))
    with pytest.raises(InvalidMechanismError, match=f"at most {MAX_LAYERED_JOINTS} joints"):
        find_collisions(adjacency, node_types, positions, **SIZE)
