"""The dyadic solver against independent truth (docs/reference/contract.md, Simulation).

* Four-bar linkages against the closed-form Freudenstein solution: coupler curves of Grashof
  crank-rockers to ~1e-9, and the exact first locking step of four-bars whose crank cannot turn.
* Hypothesis property tests on random dyadic mechanisms built with the J-operator: rigid links,
  still ground, a crank turning by exactly 2*pi/steps, step 0 = initial pose, frozen branches.
* Consistency of `simulate`, `simulate_batch`, `TopologySimulator` (serial and parallel) and of
  different step counts.
"""

from __future__ import annotations

import itertools
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from links_ray import (
    InvalidMechanismError,
    LockingError,
    TopologySimulator,
    simulate,
    simulate_batch,
)
from links_ray.engine.inputs import MAX_COORDINATE, MIN_LINK_LENGTH

TAU = 2.0 * math.pi
#: Four-bar joints: 0 = O2 (fixed pivot), 1 = A (crank tip), 2 = B (coupler/rocker), 3 = O4.
FOURBAR_LINKS = [(0, 1), (1, 2), (2, 3)]
#: The optional coupler point C (joint 4) rides on the coupler A-B.
COUPLER_LINKS = [(1, 4), (2, 4)]
#: Tangency guard: sin^2 of the Freudenstein half-opening must stay clear of zero at every step.
TANGENCY_MARGIN = 1e-8


def make_adjacency(n: int, links: list[tuple[int, int]]) -> np.ndarray:
    """Symmetric 0/1 adjacency matrix of `n` joints with the given links."""
    adjacency = np.zeros((n, n), dtype=np.int64)
    for i, j in links:
        adjacency[i, j] = adjacency[j, i] = 1
    return adjacency


def fourbar_topology(coupler: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(adjacency, node_types) of the four-bar, with coupler point C as joint 4 if asked."""
    if coupler:
        return make_adjacency(5, FOURBAR_LINKS + COUPLER_LINKS), np.array([0, 2, 1, 0, 1])
    return make_adjacency(4, FOURBAR_LINKS), np.array([0, 2, 1, 0])


def cross2(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """z-component of the cross product of 2-D vectors (broadcasting over leading axes)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def rotate(v: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Rotate 2-D vectors `v` counter-clockwise by `angle` (broadcasting)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


# --------------------------------------------------------------------------------------------
# Closed-form four-bar kinematics (Freudenstein)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Freudenstein:
    """Both closed-form solutions for the rocker angle theta4 at crank angles theta2.

    Frame: O2 at the origin, ground link O2->O4 along +x. Freudenstein's equation
    K1 cos th4 - K2 cos th2 + K3 = cos(th2 - th4) rearranged as P cos th4 + Q sin th4 = C.
    `sin2_half` = 1 - (C/R)^2 is the normalised discriminant: negative where B cannot be built.
    """

    theta4_plus: np.ndarray
    theta4_minus: np.ndarray
    sin2_half: np.ndarray


def freudenstein(theta2: np.ndarray, a: float, b: float, c: float, d: float) -> Freudenstein:
    """Solve Freudenstein's equation for crank `a`, coupler `b`, rocker `c`, ground `d`."""
    k1, k2 = d / a, d / c
    k3 = (a * a - b * b + c * c + d * d) / (2.0 * a * c)
    p = k1 - np.cos(theta2)
    q = -np.sin(theta2)
    rhs = k2 * np.cos(theta2) - k3
    r = np.hypot(p, q)
    ratio = rhs / r
    phi = np.arctan2(q, p)
    half = np.arccos(np.clip(ratio, -1.0, 1.0))
    return Freudenstein(phi + half, phi - half, 1.0 - ratio * ratio)


def fourbar_lengths(positions: np.ndarray) -> tuple[float, float, float, float]:
    """Crank, coupler, rocker and ground lengths (a, b, c, d) of four-bar positions."""
    o2, a0, b0, o4 = positions[:4]
    return (
        float(np.hypot(*(a0 - o2))),
        float(np.hypot(*(b0 - a0))),
        float(np.hypot(*(b0 - o4))),
        float(np.hypot(*(o4 - o2))),
    )


def crank_angles(positions: np.ndarray, steps: int) -> np.ndarray:
    """World crank angle at every step: theta0 + 2*pi*t/steps."""
    theta0 = math.atan2(*(positions[1] - positions[0])[::-1])
    return theta0 + TAU * np.arange(steps) / steps


def fourbar_discriminant(positions: np.ndarray, steps: int) -> np.ndarray:
    """Normalised Freudenstein discriminant at every step (negative: B cannot be assembled)."""
    a, b, c, d = fourbar_lengths(positions)
    gamma = math.atan2(*(positions[3] - positions[0])[::-1])
    return freudenstein(crank_angles(positions, steps) - gamma, a, b, c, d).sin2_half


def fourbar_truth(positions: np.ndarray, steps: int) -> np.ndarray:
    """Closed-form trajectories (n, steps, 2) of a four-bar (with optional coupler point 4).

    Of the two Freudenstein roots, B is the one on the same side of the line A -> O4 as the
    initial B. The coupler point follows rigidly from A and B.
    """
    positions = np.asarray(positions, dtype=np.float64)
    o2, a0, b0, o4 = positions[:4]
    a, b, c, d = fourbar_lengths(positions)
    gamma = math.atan2(*(o4 - o2)[::-1])
    theta = crank_angles(positions, steps)
    sol = freudenstein(theta - gamma, a, b, c, d)
    assert np.all(sol.sin2_half > 0), "the closed form says this four-bar locks"

    crank_tip = o2 + a * np.stack([np.cos(theta), np.sin(theta)], axis=-1)

    def rocker_tip(theta4: np.ndarray) -> np.ndarray:
        local = np.stack([d + c * np.cos(theta4), c * np.sin(theta4)], axis=-1)
        return o2 + rotate(local, gamma)

    b_plus, b_minus = rocker_tip(sol.theta4_plus), rocker_tip(sol.theta4_minus)
    side0 = np.sign(cross2(o4 - a0, b0 - a0))
    assert side0 != 0
    plus_ok = np.sign(cross2(o4 - crank_tip, b_plus - crank_tip)) == side0
    coupler_tip = np.where(plus_ok[:, None], b_plus, b_minus)

    out = np.empty((len(positions), steps, 2))
    out[0], out[3] = o2, o4
    out[1], out[2] = crank_tip, coupler_tip
    if len(positions) == 5:
        e0 = (b0 - a0) / b
        n0 = np.array([-e0[1], e0[0]])
        u, v = float((positions[4] - a0) @ e0), float((positions[4] - a0) @ n0)
        e = (coupler_tip - crank_tip) / b
        n = np.stack([-e[:, 1], e[:, 0]], axis=-1)
        out[4] = crank_tip + u * e + v * n
    return out


def fourbar_positions(
    o2: tuple[float, float],
    gamma: float,
    lengths: tuple[float, float, float, float],
    theta0: float,
    branch: int,
    coupler: tuple[float, float] | None = None,
) -> np.ndarray:
    """Initial positions of a four-bar assembled at crank angle `theta0` on `branch` (+1/-1).

    `coupler` = (u, v) places C at A + u * e + v * n in the coupler frame (e along A->B).
    """
    a, b, c, d = lengths
    origin = np.asarray(o2, dtype=np.float64)
    sol = freudenstein(np.array([theta0 - gamma]), a, b, c, d)
    assert sol.sin2_half[0] > 0, "cannot assemble at theta0"
    theta4 = (sol.theta4_plus if branch > 0 else sol.theta4_minus)[0]
    o4 = origin + d * np.array([math.cos(gamma), math.sin(gamma)])
    tip = origin + a * np.array([math.cos(theta0), math.sin(theta0)])
    rocker = origin + rotate(np.array([d + c * math.cos(theta4), c * math.sin(theta4)]), gamma)
    joints = [origin, tip, rocker, o4]
    if coupler is not None:
        e = (rocker - tip) / b
        joints.append(tip + coupler[0] * e + coupler[1] * np.array([-e[1], e[0]]))
    return np.array(joints)


def grashof(lengths: tuple[float, float, float, float]) -> tuple[float, int]:
    """(p + q - s - l, index of the shortest link): Grashof when the slack is >= 0."""
    ordered = sorted(lengths)
    return ordered[1] + ordered[2] - ordered[0] - ordered[3], int(np.argmin(lengths))


def random_crank_rocker(rng: np.random.Generator, coupler: bool) -> np.ndarray:
    """Positions of a random Grashof crank-rocker (crank shortest) with a safe Grashof slack."""
    while True:
        lengths = (rng.uniform(0.03, 0.3), *rng.uniform(0.1, 1.0, 3))
        slack, shortest = grashof(lengths)
        if shortest == 0 and slack > 0.05 * max(lengths):
            break
    return fourbar_positions(
        o2=tuple(rng.uniform(0.0, 1.0, 2)),
        gamma=rng.uniform(-math.pi, math.pi),
        lengths=lengths,
        theta0=rng.uniform(-math.pi, math.pi),
        branch=int(rng.choice([-1, 1])),
        coupler=tuple(rng.uniform(-0.5, 0.5, 2)) if coupler else None,
    )


def random_non_rotating_fourbar(rng: np.random.Generator) -> np.ndarray:
    """Positions of a random four-bar whose crank cannot turn fully (assembled at step 0).

    Non-Grashof four-bars, and Grashof ones whose shortest link is the coupler or the rocker.
    """
    while True:
        lengths = tuple(rng.uniform(0.05, 1.0, 4))
        slack, shortest = grashof(lengths)
        if not (slack < -0.01 or (slack > 0.01 and shortest in (1, 2))):
            continue
        # Some crank angle must assemble it, clear of tangency (d > a + b + c never does).
        grid = np.linspace(-math.pi, math.pi, 721)
        assemblable = grid[freudenstein(grid, *lengths).sin2_half > 1e-3]
        if len(assemblable):
            break
    gamma = rng.uniform(-math.pi, math.pi)
    theta0 = gamma + float(rng.choice(assemblable))
    return fourbar_positions(
        o2=tuple(rng.uniform(0.0, 1.0, 2)),
        gamma=gamma,
        lengths=lengths,
        theta0=theta0,
        branch=int(rng.choice([-1, 1])),
    )


# Hand-picked crank-rockers: (o2, gamma, (a, b, c, d), theta0, branch, coupler point)
HAND_PICKED = [
    ((0.5, 0.5), 0.0, (0.05, 0.30, 0.36, 0.30), 0.0, 1, None),
    ((0.5, 0.5), 0.0, (0.05, 0.30, 0.36, 0.30), 0.0, -1, (0.1, 0.2)),
    ((0.0, 0.0), 1.0, (1.0, 3.0, 3.5, 4.0), 2.5, 1, (1.5, -0.7)),
    ((0.0, 0.0), 1.0, (1.0, 3.0, 3.5, 4.0), 2.5, -1, (1.5, -0.7)),
    ((0.3, 0.8), -2.2, (0.1, 0.5, 0.4, 0.45), -1.0, 1, (-0.2, 0.3)),
    ((0.9, 0.1), math.pi / 2, (0.2, 0.9, 0.6, 0.7), math.pi, -1, None),
    ((-3.0, 2.0), 3.0, (2.0, 7.0, 5.0, 6.0), 0.4, 1, (0.0, 2.0)),
]


@pytest.mark.parametrize("case", HAND_PICKED, ids=lambda case: f"{case[2]}-b{case[4]}")
def test_crank_rocker_matches_freudenstein(case: tuple) -> None:
    """Hand-picked Grashof crank-rockers, both branches, various ground orientations."""
    o2, gamma, lengths, theta0, branch, coupler = case
    slack, shortest = grashof(lengths)
    assert slack > 0 and shortest == 0
    positions = fourbar_positions(o2, gamma, lengths, theta0, branch, coupler)
    adjacency, node_types = fourbar_topology(coupler is not None)
    got = simulate(adjacency, node_types, positions)
    assert got.shape == (len(positions), 200, 2) and got.dtype == np.float64
    np.testing.assert_allclose(got, fourbar_truth(positions, 200), rtol=0, atol=1e-9)


def test_branches_are_mirror_images() -> None:
    """The two assembly branches put B at mirror images across the line A -> O4 at every step."""
    lengths = (0.05, 0.30, 0.36, 0.30)
    upper = simulate(*fourbar_topology(), fourbar_positions((0.5, 0.5), 0.0, lengths, 0.0, 1))
    lower = simulate(*fourbar_topology(), fourbar_positions((0.5, 0.5), 0.0, lengths, 0.0, -1))
    assert np.all(upper[2, :, 1] > 0.5) and np.all(lower[2, :, 1] < 0.5)
    np.testing.assert_array_equal(upper[[0, 1, 3]], lower[[0, 1, 3]])
    tip, pivot = upper[1], upper[3]
    axis = (pivot - tip) / np.linalg.norm(pivot - tip, axis=-1, keepdims=True)
    offset = upper[2] - tip
    mirrored = tip + 2.0 * np.sum(offset * axis, axis=-1, keepdims=True) * axis - offset
    np.testing.assert_allclose(mirrored, lower[2], rtol=0, atol=1e-12)


@pytest.mark.parametrize("seed", range(8))
def test_random_crank_rockers_match_freudenstein(seed: int) -> None:
    """Seeded random crank-rockers (with coupler points) follow the closed form to 1e-9."""
    rng = np.random.default_rng(1000 + seed)
    adjacency, node_types = fourbar_topology(coupler=True)
    batch = np.array([random_crank_rocker(rng, coupler=True) for _ in range(16)])
    for positions in batch:  # the theory: a Grashof crank-rocker never fails to assemble
        assert fourbar_discriminant(positions, 2000).min() > 1e-4
    trajectories, valid = simulate_batch(adjacency, node_types, batch)
    assert valid.all()
    for positions, got in zip(batch, trajectories, strict=True):
        np.testing.assert_allclose(got, fourbar_truth(positions, 200), rtol=0, atol=1e-9)
        np.testing.assert_array_equal(simulate(adjacency, node_types, positions), got)


@pytest.mark.parametrize("steps", [1, 7, 50, 360])
def test_other_step_counts_match_freudenstein(steps: int) -> None:
    """Step counts other than 200 sample the same closed-form curve."""
    positions = fourbar_positions((0.5, 0.5), 0.3, (0.05, 0.3, 0.36, 0.3), 0.0, 1, (0.1, 0.2))
    got = simulate(*fourbar_topology(coupler=True), positions, steps)
    assert got.shape == (5, steps, 2)
    np.testing.assert_allclose(got, fourbar_truth(positions, steps), rtol=0, atol=1e-9)


def test_default_steps_is_200() -> None:
    """Without `steps` the simulation has 200 steps."""
    positions = fourbar_positions((0.5, 0.5), 0.0, (0.05, 0.3, 0.36, 0.3), 0.0, 1)
    assert simulate(*fourbar_topology(), positions).shape == (4, 200, 2)
    trajectories, valid = simulate_batch(*fourbar_topology(), positions[None])
    assert trajectories.shape == (1, 4, 200, 2) and valid.tolist() == [True]


def test_coarse_steps_are_a_subsample_of_fine_steps() -> None:
    """Step t of a 50-step simulation equals step 4t of a 200-step one."""
    rng = np.random.default_rng(7)
    adjacency, node_types = fourbar_topology(coupler=True)
    batch = np.array([random_crank_rocker(rng, coupler=True) for _ in range(8)])
    coarse, valid_coarse = simulate_batch(adjacency, node_types, batch, 50)
    fine, valid_fine = simulate_batch(adjacency, node_types, batch, 200)
    assert valid_coarse.all() and valid_fine.all()
    np.testing.assert_allclose(coarse, fine[:, :, ::4], rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Locking
# --------------------------------------------------------------------------------------------


def predicted_lock(positions: np.ndarray, steps: int) -> int | None:
    """First step where the Freudenstein discriminant is negative (None: never locks)."""
    negative = np.flatnonzero(fourbar_discriminant(positions, steps) < 0)
    return int(negative[0]) if len(negative) else None


def locking_cases(seed: int, count: int, steps: int) -> list[tuple[np.ndarray, int]]:
    """`count` random non-rotating four-bars with their predicted lock step, clear of tangency."""
    rng = np.random.default_rng(seed)
    cases = []
    while len(cases) < count:
        positions = random_non_rotating_fourbar(rng)
        disc = fourbar_discriminant(positions, steps)
        step = predicted_lock(positions, steps)
        if step is not None and np.abs(disc).min() > TANGENCY_MARGIN:
            cases.append((positions, step))
    return cases


def test_non_rotating_fourbars_do_lock_in_closed_form() -> None:
    """Sanity check of the generator: most of its four-bars lock within one crank turn."""
    rng = np.random.default_rng(3)
    locks = [predicted_lock(random_non_rotating_fourbar(rng), 2000) for _ in range(200)]
    assert sum(step is not None for step in locks) >= 190


@pytest.mark.parametrize("steps", [50, 200])
def test_lock_step_matches_freudenstein(steps: int) -> None:
    """`simulate` raises LockingError at the closed-form first locking step, joint 2."""
    adjacency, node_types = fourbar_topology()
    for positions, step in locking_cases(seed=steps, count=25, steps=steps):
        assert step > 0
        with pytest.raises(LockingError) as info:
            simulate(adjacency, node_types, positions, steps)
        assert (info.value.step, info.value.node) == (step, 2)
        assert isinstance(info.value, ValueError)


def test_lock_with_coupler_point_reports_joint_2() -> None:
    """A coupler point riding on a locking coupler does not change the reported lock."""
    adjacency, node_types = fourbar_topology(coupler=True)
    for positions, step in locking_cases(seed=11, count=10, steps=200):
        a0, b0 = positions[1], positions[2]
        c0 = a0 + rotate(b0 - a0, 0.7) * 0.6
        with pytest.raises(LockingError) as info:
            simulate(adjacency, node_types, np.vstack([positions, c0]))
        assert (info.value.step, info.value.node) == (step, 2)


def test_batch_and_first_lock_agree_on_locking() -> None:
    """In one batch: locking rows are invalid and all-NaN, rotating rows valid and finite."""
    adjacency, node_types = fourbar_topology()
    locking = locking_cases(seed=5, count=12, steps=200)
    rng = np.random.default_rng(5)
    rotating = [random_crank_rocker(rng, coupler=False) for _ in range(12)]
    batch = np.array(
        [p for pair in zip(rotating, locking, strict=True) for p in (pair[0], pair[1][0])]
    )
    expected_valid = np.tile([True, False], 12)

    trajectories, valid = simulate_batch(adjacency, node_types, batch)
    assert valid.dtype == np.bool_ and valid.shape == (24,)
    np.testing.assert_array_equal(valid, expected_valid)
    assert np.isnan(trajectories[~valid]).all()
    assert np.isfinite(trajectories[valid]).all()
    for positions, got in zip(batch[valid], trajectories[valid], strict=True):
        np.testing.assert_allclose(got, fourbar_truth(positions, 200), rtol=0, atol=1e-9)

    lock_step, lock_node = TopologySimulator(adjacency, node_types).first_lock(batch)
    np.testing.assert_array_equal(lock_step[valid], -1)
    np.testing.assert_array_equal(lock_node[valid], -1)
    np.testing.assert_array_equal(lock_step[~valid], [step for _, step in locking])
    np.testing.assert_array_equal(lock_node[~valid], 2)


# --------------------------------------------------------------------------------------------
# Property tests on random dyadic mechanisms (J-operator)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Dyadic:
    """A J-operator mechanism: topology plus the two construction parents of each simple joint."""

    adjacency: np.ndarray
    node_types: np.ndarray
    parents: dict[int, tuple[int, int]]


@st.composite
def dyadic_mechanisms(draw: st.DrawFn) -> Dyadic:
    """Joints 0 fixed, 1 actuated, 2 fixed, link (0, 1); then 1-5 fixed or simple joints.

    A simple joint is linked to two existing joints that are not both fixed.
    """
    node_types = [0, 2, 0]
    links = [(0, 1)]
    parents: dict[int, tuple[int, int]] = {}
    for _ in range(draw(st.integers(1, 5), label="new joints")):
        n = len(node_types)
        if draw(st.integers(0, 3), label="kind") == 0:
            node_types.append(0)
            continue
        moving = [j for j in range(n) if node_types[j] != 0]
        first = draw(st.sampled_from(moving), label="first parent")
        second = draw(st.sampled_from([j for j in range(n) if j != first]), label="second")
        a, b = sorted((first, second))
        parents[n] = (a, b)
        node_types.append(1)
        links += [(a, n), (b, n)]
    n = len(node_types)
    return Dyadic(make_adjacency(n, links), np.array(node_types), parents)


def candidate_positions(rng: np.random.Generator, n: int, count: int) -> np.ndarray:
    """`count` random position sets in [0, 1]^2 with a crank of length 0.03-0.2."""
    positions = rng.uniform(0.0, 1.0, (count, n, 2))
    radius = rng.uniform(0.03, 0.2, count)
    angle = rng.uniform(-math.pi, math.pi, count)
    positions[:, 1] = positions[:, 0] + radius[:, None] * np.stack(
        [np.cos(angle), np.sin(angle)], axis=-1
    )
    return positions


def well_conditioned(positions: np.ndarray, parents: dict[int, tuple[int, int]]) -> np.ndarray:
    """Mask of position sets whose simple joints are clear of their parents' line (sin > 0.05)."""
    ok = np.ones(len(positions), dtype=bool)
    for j, (a, b) in parents.items():
        to_a = positions[:, a] - positions[:, j]
        to_b = positions[:, b] - positions[:, j]
        sine = np.abs(cross2(to_a, to_b)) / (
            np.linalg.norm(to_a, axis=-1) * np.linalg.norm(to_b, axis=-1)
        )
        ok &= sine > 0.05
    return ok


def valid_batch(mechanism: Dyadic, seed: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Well-conditioned random candidates and their valid trajectories (at least one)."""
    n = len(mechanism.node_types)
    positions = candidate_positions(np.random.default_rng(seed), n, 256)
    positions = positions[well_conditioned(positions, mechanism.parents)]
    trajectories, valid = simulate_batch(
        mechanism.adjacency, mechanism.node_types, positions, steps
    )
    assert np.isnan(trajectories[~valid]).all() and np.isfinite(trajectories[valid]).all()
    return positions[valid], trajectories[valid]


PROPERTY_SETTINGS = settings(
    max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)


@PROPERTY_SETTINGS
@given(
    mechanism=dyadic_mechanisms(),
    seed=st.integers(0, 2**32 - 1),
    steps=st.sampled_from([7, 50, 200]),
)
def test_dyadic_mechanism_properties(mechanism: Dyadic, seed: int, steps: int) -> None:
    """Rigid links, still ground, exact crank turns, step 0 = initial pose, frozen branches."""
    positions, trajectories = valid_batch(mechanism, seed, steps)
    assert len(positions) > 0, "no valid candidate among 256"
    adjacency, node_types = mechanism.adjacency, mechanism.node_types
    assert trajectories.shape == (len(positions), len(node_types), steps, 2)

    # The solver solves each simple joint from its two construction parents.
    order = TopologySimulator(adjacency, node_types).topology.order
    assert {int(j): (int(a), int(b)) for j, a, b in order} == mechanism.parents

    # Step 0 is the initial pose.
    np.testing.assert_allclose(trajectories[:, :, 0], positions, rtol=0, atol=1e-12)

    # Every link keeps its initial length.
    for i, j in np.argwhere(np.triu(adjacency, 1)):
        initial = np.linalg.norm(positions[:, i] - positions[:, j], axis=-1)
        length = np.linalg.norm(trajectories[:, i] - trajectories[:, j], axis=-1)
        assert np.max(np.abs(length / initial[:, None] - 1.0)) < 1e-9, (i, j)

    # Fixed joints never move.
    for f in np.flatnonzero(node_types == 0):
        expected = np.broadcast_to(positions[:, f, None], trajectories[:, f].shape)
        np.testing.assert_array_equal(trajectories[:, f], expected)

    # The crank tip turns counter-clockwise about joint 0 by exactly 2*pi/steps per step.
    arm0 = positions[:, 1] - positions[:, 0]
    turn = TAU * np.arange(steps) / steps
    expected_tip = positions[:, None, 0] + rotate(arm0[:, None], turn[None, :])
    np.testing.assert_allclose(trajectories[:, 1], expected_tip, rtol=0, atol=1e-12)
    arm = trajectories[:, 1] - trajectories[:, 0]
    step_angle = np.arctan2(
        cross2(arm[:, :-1], arm[:, 1:]), np.sum(arm[:, :-1] * arm[:, 1:], axis=-1)
    )
    np.testing.assert_allclose(step_angle, TAU / steps, rtol=0, atol=1e-12)

    # Each simple joint stays on its initial side of the line parent_a -> parent_b.
    for j, (a, b) in mechanism.parents.items():
        side0 = np.sign(
            cross2(positions[:, b] - positions[:, a], positions[:, j] - positions[:, a])
        )
        side = cross2(
            trajectories[:, b] - trajectories[:, a], trajectories[:, j] - trajectories[:, a]
        )
        assert np.all(side * side0[:, None] > -1e-12), j


@PROPERTY_SETTINGS
@given(mechanism=dyadic_mechanisms(), seed=st.integers(0, 2**32 - 1))
def test_batch_simulate_and_first_lock_agree(mechanism: Dyadic, seed: int) -> None:
    """simulate_batch = TopologySimulator.simulate = simulate row by row = first_lock."""
    adjacency, node_types = mechanism.adjacency, mechanism.node_types
    positions = candidate_positions(np.random.default_rng(seed), len(node_types), 24)
    trajectories, valid = simulate_batch(adjacency, node_types, positions, 50)
    simulator = TopologySimulator(adjacency, node_types)
    lock_step, lock_node = simulator.first_lock(positions, 50)
    np.testing.assert_array_equal(lock_step < 0, valid)

    for k in range(len(positions)):
        if valid[k]:
            np.testing.assert_array_equal(
                simulate(adjacency, node_types, positions[k], 50), trajectories[k]
            )
            assert lock_node[k] == -1
        else:
            assert np.isnan(trajectories[k]).all()
            with pytest.raises(LockingError) as info:
                simulate(adjacency, node_types, positions[k], 50)
            assert (info.value.step, info.value.node) == (lock_step[k], lock_node[k])
            # A lock after the last step (before the turn closes) is reported at step 50.
            assert 0 < info.value.step <= 50 and node_types[info.value.node] == 1

    serial, serial_valid = simulator.simulate(positions, 50)
    np.testing.assert_array_equal(serial_valid, valid)
    np.testing.assert_array_equal(serial, trajectories)


def simulate_in_threads(
    simulator: TopologySimulator, positions: np.ndarray, steps: int, threads: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """`simulator.simulate` over interleaved slices of the batch, one thread per slice."""
    slices = [np.arange(k, len(positions), threads) for k in range(threads)]
    with ThreadPoolExecutor(threads) as pool:
        results = list(pool.map(lambda rows: simulator.simulate(positions[rows], steps), slices))
    trajectories = np.empty((len(positions), simulator.n_joints, steps, 2))
    valid = np.empty(len(positions), dtype=bool)
    for rows, (part, part_valid) in zip(slices, results, strict=True):
        trajectories[rows], valid[rows] = part, part_valid
    return trajectories, valid


def test_threaded_simulation_equals_serial() -> None:
    """One simulator shared by threads (the kernels drop the GIL) gives the serial result."""
    adjacency, node_types = fourbar_topology(coupler=True)
    rng = np.random.default_rng(17)
    batch = np.array(
        [random_crank_rocker(rng, coupler=True) for _ in range(40)]
        + [np.vstack([p, p[1] + 0.1]) for p, _ in locking_cases(seed=17, count=24, steps=200)]
    )
    simulator = TopologySimulator(adjacency, node_types)
    serial, serial_valid = simulator.simulate(batch)
    assert serial_valid[:40].all() and not serial_valid[40:].any()
    for _ in range(3):
        threaded, threaded_valid = simulate_in_threads(simulator, batch, 200)
        np.testing.assert_array_equal(threaded_valid, serial_valid)
        np.testing.assert_array_equal(threaded, serial)


def test_lock_step_is_the_first_one() -> None:
    """first_lock reports the first step the closed form cannot assemble, not a later one."""
    mechanism_adj, mechanism_types = fourbar_topology()
    simulator = TopologySimulator(mechanism_adj, mechanism_types)
    for positions, step in locking_cases(seed=21, count=10, steps=200):
        # Every step before the lock is assemblable in closed form, the lock step is not.
        disc = fourbar_discriminant(positions, 200)
        assert np.all(disc[:step] > 0) and disc[step] < 0
        lock_step, lock_node = simulator.first_lock(positions[None], 200)
        assert (int(lock_step[0]), int(lock_node[0])) == (step, 2)


def test_single_step_is_the_initial_pose() -> None:
    """With steps=1 the only pose is the initial one."""
    positions = fourbar_positions((0.5, 0.5), 0.2, (0.05, 0.3, 0.36, 0.3), 1.0, -1, (0.1, 0.2))
    got = simulate(*fourbar_topology(coupler=True), positions, 1)
    assert got.shape == (5, 1, 2)
    np.testing.assert_allclose(got[:, 0], positions, rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Degenerate geometry, scale and threads
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 1e3, 1e6])
def test_scale_invariance(scale: float) -> None:
    """Scaling a mechanism scales its trajectories (and keeps it valid)."""
    rng = np.random.default_rng(23)
    adjacency, node_types = fourbar_topology(coupler=True)
    batch = np.array([random_crank_rocker(rng, coupler=True) for _ in range(8)])
    reference, valid = simulate_batch(adjacency, node_types, batch)
    scaled, scaled_valid = simulate_batch(adjacency, node_types, batch * scale)
    assert valid.all() and scaled_valid.all()
    np.testing.assert_allclose(scaled / scale, reference, rtol=0, atol=1e-9)


def test_parents_passing_through_each_other_lock() -> None:
    """The crank tip passes exactly over fixed joint 3 at step 50: joint 2 (equal radii to both)
    cannot be placed there, so the four-bar locks at step 50, joint 2."""
    adjacency, node_types = fourbar_topology()
    positions = np.array([[0.5, 0.5], [0.75, 0.5], [0.9, 0.9], [0.5, 0.75]])
    simulator = TopologySimulator(adjacency, node_types)
    tip = positions[0] + rotate(positions[1] - positions[0], TAU * 50 / 200)
    assert np.array_equal(np.round(tip, 15), positions[3])
    lock_step, lock_node = simulator.first_lock(positions[None])
    assert (int(lock_step[0]), int(lock_node[0])) == (50, 2)
    trajectories, valid = simulate_batch(adjacency, node_types, positions[None])
    assert not valid[0] and np.isnan(trajectories).all()
    with pytest.raises(LockingError) as info:
        simulate(adjacency, node_types, positions)
    assert (info.value.step, info.value.node) == (50, 2)


def edge_scales(positions: np.ndarray, adjacency: np.ndarray) -> tuple[float, float]:
    """The least and greatest factors by which `positions` may be scaled and still be taken:
    the shortest link just over MIN_LINK_LENGTH, the farthest coordinate just under
    MAX_COORDINATE."""
    i, j = np.nonzero(np.triu(adjacency, 1))
    shortest = np.linalg.norm(positions[i] - positions[j], axis=1).min()
    return MIN_LINK_LENGTH / shortest * 1.001, MAX_COORDINATE / np.abs(positions).max() * 0.999


@pytest.mark.parametrize("edge", ["smallest", "largest"])
def test_scales_at_the_edges_of_the_accepted_range(edge: str) -> None:
    """At the smallest and largest scales the checks accept, trajectories are finite and are the
    unit-scale ones scaled."""
    adjacency, node_types = fourbar_topology()
    positions = fourbar_positions((0.5, 0.5), 0.0, (0.05, 0.3, 0.36, 0.3), 0.0, 1)
    reference = simulate(adjacency, node_types, positions)
    smallest, largest = edge_scales(positions, adjacency)
    scale = smallest if edge == "smallest" else largest
    trajectories, valid = simulate_batch(adjacency, node_types, positions[None] * scale)
    assert valid[0] and np.isfinite(trajectories).all()
    np.testing.assert_allclose(trajectories[0] / scale, reference, rtol=0, atol=1e-9)
    single = simulate(adjacency, node_types, positions * scale)
    np.testing.assert_array_equal(single, trajectories[0])


@pytest.mark.parametrize(
    ("where", "match"),
    [
        ("just above the largest", r"positions must lie within \+-1e\+12"),
        ("far above the largest", r"positions must lie within \+-1e\+12"),
        ("just below the smallest", r"crank has zero length: joints 0 and 1 are closer than 1e-09"),
        ("far below the smallest", r"crank has zero length: joints 0 and 1 are closer than 1e-09"),
    ],
)
def test_scales_beyond_the_accepted_range_are_refused(where: str, match: str) -> None:
    """Just past either edge, and far past it, the input is refused, naming the limit."""
    adjacency, node_types = fourbar_topology()
    positions = fourbar_positions((0.5, 0.5), 0.0, (0.05, 0.3, 0.36, 0.3), 0.0, 1)
    smallest, largest = edge_scales(positions, adjacency)
    scale = {
        "just above the largest": largest * 1.002,
        "far above the largest": 1e155,
        "just below the smallest": smallest * 0.998,
        "far below the smallest": 1e-160,
    }[where]
    with pytest.raises(InvalidMechanismError, match=match):
        simulate_batch(adjacency, node_types, positions[None] * scale)
    with pytest.raises(InvalidMechanismError, match=match):
        simulate(adjacency, node_types, positions * scale)


def test_packed_mechanisms_trace_as_the_simulator_does_bit_for_bit() -> None:
    """`MechanismBank` packs mechanisms of many topologies as positions and solution paths;
    tracing any joint of them equals the topology simulator's trajectory exactly, and the
    packed mechanism unpacks to the one given."""
    import pyarrow as pa

    from links_ray.engine.kinematics.sampling import PositionSampler
    from links_ray.engine.kinematics.solver import TopologySimulator
    from links_ray.engine.kinematics.topology import random_topology
    from links_ray.search.mechanisms import MechanismBank

    rng = np.random.default_rng(17)
    mechanisms = []
    while len(mechanisms) < 12:
        adjacency, node_types = random_topology(rng)
        simulator = TopologySimulator(adjacency, node_types)
        found = PositionSampler(simulator).search(2, rng, "sequential")
        for positions, trajectories in zip(found.positions, found.trajectories, strict=True):
            mechanisms.append((adjacency, node_types, positions, trajectories))
    ids = rng.permutation(1000)[: len(mechanisms)] * 7
    table = pa.table(
        {
            "mechanism_id": ids,
            "adjacency": [m[0].ravel().tolist() for m in mechanisms],
            "node_types": [m[1].tolist() for m in mechanisms],
            "positions": [m[2].ravel().tolist() for m in mechanisms],
        }
    )
    bank = MechanismBank.from_table(table)
    assert bank.ids.tolist() == sorted(ids.tolist())
    rows = bank.rows_of(ids)
    for row, (adjacency, node_types, positions, trajectories) in zip(rows, mechanisms, strict=True):
        joints = np.arange(len(node_types))
        traced = bank.trajectories(np.full(len(joints), row), joints, trajectories.shape[1])
        np.testing.assert_array_equal(traced, trajectories)
        unpacked = bank.mechanism(row)
        np.testing.assert_array_equal(unpacked[0], adjacency)
        np.testing.assert_array_equal(unpacked[1], node_types)
        np.testing.assert_array_equal(unpacked[2], positions)
    with pytest.raises(ValueError, match="mechanism 5 is not in the mechanisms table"):
        bank.rows_of(np.array([5]))


def test_a_bank_packed_table_by_table_is_the_bank_of_their_rows() -> None:
    """`MechanismBank.from_tables` packs tables one at a time, in any order of ids within and
    across them; the bank is the one packed from all their rows at once, array for array."""
    import pyarrow as pa

    from links_ray.engine.kinematics.sampling import PositionSampler
    from links_ray.engine.kinematics.solver import TopologySimulator
    from links_ray.engine.kinematics.topology import random_topology
    from links_ray.search.mechanisms import MechanismBank

    rng = np.random.default_rng(23)
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    while len(rows) < 30:
        adjacency, node_types = random_topology(rng)
        simulator = TopologySimulator(adjacency, node_types)
        found = PositionSampler(simulator).search(3, rng, "sequential")
        rows += [(adjacency, node_types, positions) for positions in found.positions]
    ids = rng.permutation(10_000)[: len(rows)]
    table = pa.table(
        {
            "mechanism_id": ids,
            "adjacency": [row[0].ravel().tolist() for row in rows],
            "node_types": [row[1].tolist() for row in rows],
            "positions": [row[2].ravel().tolist() for row in rows],
        }
    )
    whole = MechanismBank.from_table(table.sort_by("mechanism_id"))
    cuts = [0, 4, 5, 17, 29, len(rows)]
    tables = [table.slice(a, b - a) for a, b in itertools.pairwise(cuts)]
    parted = MechanismBank.from_tables(tables[::-1])
    for name, array in whole.arrays().items():
        np.testing.assert_array_equal(parted.arrays()[name], array, err_msg=name)
        assert parted.arrays()[name].dtype == array.dtype, name
    assert len(MechanismBank.from_tables([])) == 0
    with pytest.raises(ValueError, match="holds a mechanism_id twice"):
        MechanismBank.from_tables([tables[1], tables[2], tables[1]])
