"""Refinement (engine.synthesis.refinement.loop, engine.synthesis.refinement.kernels) against
independent truth.

* The kernel's trajectories equal `simulate`'s bit for bit, its locks `first_lock`'s; its
  derivatives equal central finite differences; its transmission sines equal the angle at each
  solved joint measured from `simulate`'s trajectories.
* A closed-form four-bar (Freudenstein, tests/engine/kinematics/test_solver.py): refining a
  perturbed copy toward the original's coupler curve brings the chamfer to about 0, in any frame.
* On random mechanisms refinement never raises the chamfer, and the result turns at 2,000
  steps, keeps every branch and keeps the transmission margin, all measured from `simulate`.
* A third of a known path, as a partial stroke, finds a run of steps overlapping the true one.
* Bad input raises ValueError naming the problem.
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
import pytest

import links_ray
from links_ray import LockingError, TopologySimulator, chamfer, random_topology, simulate
from links_ray.engine.inputs import MAX_TRANSMISSION_DEG, MIN_POINTS
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.engine.kinematics.paths import longest_chord
from links_ray.engine.kinematics.solver import crank_table, dyad_geometry
from links_ray.engine.synthesis.limits import (
    MAX_REFINE_JOINTS,
    MAX_REFINE_STEPS,
    REFINE_CHECK_STEPS,
)
from links_ray.engine.synthesis.refinement import checks as refine_checks
from links_ray.engine.synthesis.refinement import loop as refine_module
from links_ray.engine.synthesis.refinement.entry import refine, refine_many
from links_ray.engine.synthesis.refinement.kernels import (
    best_interval,
    nearest_pairs,
    solve_tangents,
)
from links_ray.engine.synthesis.refinement.loop import refine_validated
from links_ray.engine.synthesis.refinement.step_kernels import guarded_minimum
from links_ray.engine.synthesis.target import as_target
from tests.engine.kinematics.test_solver import (
    fourbar_positions,
    fourbar_topology,
    fourbar_truth,
    grashof,
)

#: A Grashof crank-rocker with a coupler point, transmission angle 54 to 100 degrees.
GOOD_FOURBAR = ((0.2, 0.1), 0.3, (0.1, 0.35, 0.3, 0.4), 0.7, 1, (0.15, 0.12))
#: One whose transmission angle falls to about 31 degrees.
LOW_FOURBAR = ((0.2, 0.1), 0.3, (0.15, 0.3, 0.25, 0.38), 0.7, 1, (0.15, 0.12))


def solve(
    adjacency: np.ndarray, node_types: np.ndarray, positions: np.ndarray, steps: int, tangents: bool
) -> tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(lock, traj, dtraj, trans, dtrans) of the kernel."""
    topology = analyze_topology(adjacency, node_types)
    n, m = topology.n_joints, len(topology.order)
    cols = 2 * n if tangents else 0
    traj, dtraj = np.empty((n, steps, 2)), np.empty((n, steps, 2, cols))
    trans, dtrans = np.empty((m, steps)), np.empty((m, steps, cols))
    lock = solve_tangents(
        topology.order,
        topology.fixed_joints,
        np.ascontiguousarray(positions, dtype=np.float64),
        crank_table(steps),
        traj,
        dtraj,
        trans,
        dtrans,
        np.empty((m, 3)),
    )
    return (int(lock[0]), int(lock[1])), traj, dtraj, trans, dtrans


def angle_sines(order: np.ndarray, traj: np.ndarray) -> np.ndarray:
    """(m, steps): |sin| of the angle at each solved joint between its links to its parents."""
    u = traj[order[:, 1]] - traj[order[:, 0]]
    v = traj[order[:, 2]] - traj[order[:, 0]]
    cross = u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
    return np.abs(cross) / (np.linalg.norm(u, axis=-1) * np.linalg.norm(v, axis=-1))


def rigid_dyads(order: np.ndarray, traj: np.ndarray) -> np.ndarray:
    """(m,) bool: the parents of the dyad keep their distance over the turn."""
    gap = np.linalg.norm(traj[order[:, 2]] - traj[order[:, 1]], axis=-1)
    return np.ptp(gap, axis=1) <= 1e-9 * gap.max(axis=1)


def random_mechanisms(seed: int, count: int, low: int = 6, high: int = 15) -> list[tuple]:
    """`count` valid random mechanisms (adjacency, node_types, positions) of low-high joints."""
    rng = np.random.default_rng(seed)
    found = []
    for n in rng.integers(low, high + 1, size=count):
        adjacency, node_types = random_topology(rng, n_joints=int(n))
        positions = links_ray.sample_positions(adjacency, node_types, 1, seed=rng)[0]
        found.append((adjacency, node_types, positions))
    return found


def fourbar(case: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    o2, gamma, lengths, theta0, branch, coupler = case
    slack, shortest = grashof(lengths)
    assert slack > 0 and shortest == 0, "not a Grashof crank-rocker"
    adjacency, node_types = fourbar_topology(coupler=True)
    return adjacency, node_types, fourbar_positions(o2, gamma, lengths, theta0, branch, coupler)


def chord(points: np.ndarray) -> float:
    i, j = longest_chord(points)
    return float(np.linalg.norm(points[j] - points[i]))


# -- the kernel ---------------------------------------------------------------------------------


@pytest.mark.parametrize("steps", [1, 7, 200])
def test_trajectories_equal_simulate(steps: int) -> None:
    for adjacency, node_types, positions in random_mechanisms(0, 8):
        truth = simulate(adjacency, node_types, positions, steps)
        for tangents in (False, True):
            lock, traj, _, _, _ = solve(adjacency, node_types, positions, steps, tangents)
            assert lock == (-1, -1)
            np.testing.assert_array_equal(traj, truth)


def test_locks_equal_first_lock() -> None:
    rng = np.random.default_rng(1)
    locked = 0
    for _ in range(20):
        adjacency, node_types = random_topology(rng, n_joints=int(rng.integers(6, 16)))
        candidates = rng.uniform(0, 1, (10, len(node_types), 2))
        step, node = TopologySimulator(adjacency, node_types).first_lock(candidates)
        for b in range(len(candidates)):
            lock, *_ = solve(adjacency, node_types, candidates[b], 200, False)
            assert lock == (int(step[b]), int(node[b]))
            locked += step[b] >= 0
    assert locked > 50  # most random candidates lock: the comparison covered locks


def test_transmission_is_the_angle_at_the_joint() -> None:
    for adjacency, node_types, positions in random_mechanisms(2, 6):
        order = analyze_topology(adjacency, node_types).order
        _, _, _, trans, _ = solve(adjacency, node_types, positions, 200, False)
        truth = angle_sines(order, simulate(adjacency, node_types, positions))
        np.testing.assert_allclose(trans, truth, rtol=1e-7, atol=1e-9)


def test_derivatives_equal_finite_differences() -> None:
    checked = 0
    for adjacency, node_types, positions in random_mechanisms(3, 12):
        order = analyze_topology(adjacency, node_types).order
        _, traj, dtraj, trans, dtrans = solve(adjacency, node_types, positions, 60, True)
        moving = ~rigid_dyads(order, traj)
        # Near a dead centre the derivatives are unbounded and differences meaningless.
        if moving.any() and trans[moving].min() < 0.05:
            continue
        h = 1e-6
        n = len(positions)
        for q in range(2 * n):
            bump = np.zeros(2 * n)
            bump[q] = h
            bump = bump.reshape(n, 2)
            lock_p, traj_p, _, trans_p, _ = solve(
                adjacency, node_types, positions + bump, 60, False
            )
            lock_m, traj_m, _, trans_m, _ = solve(
                adjacency, node_types, positions - bump, 60, False
            )
            assert lock_p == lock_m == (-1, -1)
            fd = (traj_p - traj_m) / (2 * h)
            scale = 1.0 + np.abs(fd).max()
            np.testing.assert_allclose(dtraj[..., q], fd, rtol=0, atol=1e-6 * scale)
            fd_trans = (trans_p - trans_m) / (2 * h)
            scale = 1.0 + np.abs(fd_trans).max()
            np.testing.assert_allclose(dtrans[..., q], fd_trans, rtol=0, atol=1e-5 * scale)
        checked += 1
    assert checked >= 6


def test_crank_and_ground_derivatives() -> None:
    """The crank tip depends on joints 0 and 1 only, a fixed joint on itself only."""
    adjacency, node_types, positions = random_mechanisms(4, 1, 8, 8)[0]
    _, _, dtraj, _, _ = solve(adjacency, node_types, positions, 50, True)
    assert np.all(dtraj[1][..., 4:] == 0)
    assert np.all(dtraj[0] == np.eye(2, 2 * len(positions))[None])


def test_best_interval_is_exhaustive() -> None:
    rng = np.random.default_rng(5)
    path = rng.uniform(0, 1, (23, 2))
    stroke = rng.uniform(0, 1, (9, 2))
    start, count, value = best_interval(path, stroke, 3)
    values = {
        (s, c): chamfer(stroke, path[(s + np.arange(c)) % 23])
        for s in range(23)
        for c in range(3, 24)
    }
    assert value == pytest.approx(min(values.values()), rel=1e-12)
    assert values[(start, count)] == pytest.approx(value, rel=1e-12)


def _all_runs(path: np.ndarray, stroke: np.ndarray, least: int) -> dict[tuple[int, int], float]:
    """Brute force: the chamfer of every cyclic run of `path` of `least` points or more."""
    steps = len(path)
    return {
        (s, c): chamfer(stroke, path[(s + np.arange(c)) % steps])
        for s in range(steps)
        for c in range(least, steps + 1)
    }


@pytest.mark.parametrize("seed", range(6))
def test_best_interval_finds_a_stroke_along_part_of_a_path(seed: int) -> None:
    """A noisy stroke along a share of a smooth closed path, the case whose runs the search
    skips most of: the run it finds is the least of all, by brute force."""
    rng = np.random.default_rng(seed)
    steps = 48
    t = np.linspace(0, 2 * np.pi, steps, endpoint=False)
    path = np.stack([np.cos(t) + 0.3 * np.cos(3 * t), np.sin(t) + 0.2 * np.sin(2 * t)], axis=1)
    first = rng.uniform(0, 2 * np.pi)
    u = np.linspace(first, first + rng.uniform(0.2, 1.0) * 2 * np.pi, 70)
    stroke = np.stack([np.cos(u) + 0.3 * np.cos(3 * u), np.sin(u) + 0.2 * np.sin(2 * u)], axis=1)
    stroke += rng.normal(0, 0.01, stroke.shape)
    start, count, value = best_interval(path, stroke, 3)
    values = _all_runs(path, stroke, 3)
    assert value == pytest.approx(min(values.values()), rel=1e-12)
    assert values[(start, count)] == pytest.approx(value, rel=1e-12)
    assert count < steps  # a share of the path, not all of it


def test_best_interval_is_exhaustive_at_every_small_size() -> None:
    """Paths of 1 to 13 steps (odd and even: long runs are read from tables split at the
    middle), strokes of 1 to 11 points, least counts 0 to 4, random and along the path."""
    rng = np.random.default_rng(17)
    for _ in range(300):
        steps, points, least = (
            int(rng.integers(1, 14)),
            int(rng.integers(1, 12)),
            int(rng.integers(0, 5)),
        )
        if least > steps:
            continue
        if rng.random() < 0.5:
            path, stroke = rng.uniform(0, 1, (steps, 2)), rng.uniform(0, 1, (points, 2))
        else:
            t = np.linspace(0, 2 * np.pi, steps, endpoint=False)
            path = np.stack([np.cos(t), np.sin(2 * t)], axis=1)
            u = rng.uniform(0, 2 * np.pi) + np.linspace(0, rng.uniform(0.1, 1) * 2 * np.pi, points)
            stroke = np.stack([np.cos(u), np.sin(2 * u)], axis=1) + rng.normal(0, 0.02, (points, 2))
        start, count, value = best_interval(path, stroke, least)
        values = _all_runs(path, stroke, max(least, 1))
        assert value == pytest.approx(min(values.values()), rel=1e-12, abs=1e-15)
        assert values[(start, count)] == pytest.approx(value, rel=1e-12, abs=1e-15)


def test_best_interval_breaks_ties_by_the_shortest_run_then_the_lowest_start() -> None:
    """A path that runs its loop twice has equal runs half a turn apart: the lowest start wins
    whichever start the search takes first."""
    rng = np.random.default_rng(11)
    loop = rng.uniform(0, 1, (15, 2))
    path = np.concatenate([loop, loop])
    stroke = loop[4:9] + rng.normal(0, 0.01, (5, 2))
    start, count, value = best_interval(path, stroke, 3)
    values = _all_runs(path, stroke, 3)
    least = min(values.values())
    assert value == pytest.approx(least, rel=1e-12)
    tied = [run for run, v in values.items() if v <= least * (1 + 1e-12)]
    assert (count, start) == min((c, s) for s, c in tied)
    assert start < 15


# -- refinement ---------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_fourbar_recovers_its_coupler_curve(seed: int) -> None:
    """Joints moved by about 0.13% of the curve's chord: back to the exact curve. (Moved ten
    times more, about one start in three ends in a local minimum of the point chamfer near
    0.0025, a path sampled at other crank phases: see the next test.)"""
    adjacency, node_types, positions = fourbar(GOOD_FOURBAR)
    target = fourbar_truth(positions, 200)[4]  # closed form, not the solver
    rng = np.random.default_rng(seed)
    start = positions + rng.normal(0.0, 3e-4, positions.shape)
    result = refine(adjacency, node_types, start, 4, target)
    assert result.chamfer_before > 1e-3
    assert result.chamfer_after < 1e-6
    assert result.interval is None


def test_fourbar_recovery_in_any_frame() -> None:
    """Placement and scale are joint positions too: the same problem drawn 300 times larger,
    turned and moved far away is solved as well."""
    adjacency, node_types, positions = fourbar(GOOD_FOURBAR)
    turn = np.array([[math.cos(2.0), -math.sin(2.0)], [math.sin(2.0), math.cos(2.0)]]) * 300.0
    placed = positions @ turn.T + np.array([5e3, -2e3])
    target = fourbar_truth(placed, 200)[4]
    start = placed + np.random.default_rng(7).normal(0.0, 0.09, placed.shape)
    result = refine(adjacency, node_types, start, 4, target)
    assert result.chamfer_before > 1e-3
    assert result.chamfer_after < 1e-6


def test_larger_perturbations_improve_and_stay_valid() -> None:
    adjacency, node_types, positions = fourbar(GOOD_FOURBAR)
    target = fourbar_truth(positions, 200)[4]
    rng = np.random.default_rng(11)
    for _ in range(4):
        start = positions + rng.normal(0.0, 1e-2, positions.shape)
        result = refine(adjacency, node_types, start, 4, target)
        assert result.chamfer_after < 0.5 * result.chamfer_before
        assert_valid(adjacency, node_types, start, result.positions, 3.0)


def assert_valid(
    adjacency: np.ndarray,
    node_types: np.ndarray,
    start: np.ndarray,
    refined: np.ndarray,
    min_transmission_deg: float,
) -> None:
    """The refined mechanism turns at 2,000 steps, keeps the branches of `start`, and keeps the
    margin on each dyad, rigid ones too (or, one below it at the start, half its starting
    sine)."""
    order = analyze_topology(adjacency, node_types).order
    traj = simulate(adjacency, node_types, refined, REFINE_CHECK_STEPS)  # raises if it locks
    before = simulate(adjacency, node_types, start, REFINE_CHECK_STEPS)
    sides = np.empty((2, len(order), 3))
    dyad_geometry(order, start, sides[0])
    dyad_geometry(order, refined, sides[1])
    np.testing.assert_array_equal(sides[0, :, 2], sides[1, :, 2])
    margin = math.sin(math.radians(min_transmission_deg))
    start_least = angle_sines(order, before).min(axis=1)
    floor = np.where(start_least >= margin, margin, 0.5 * start_least)
    least = angle_sines(order, traj).min(axis=1)
    assert np.all(least >= floor - 1e-9)


def test_a_start_refined_from_an_origin_keeps_the_origins_floors_and_branches() -> None:
    """Synthesis shakes a refined mechanism and refines it again from there: a shaken start
    nearer a dead centre than its origin's margin, or on another branch, is refused rather
    than handed back."""
    adjacency, node_types, origin = fourbar(GOOD_FOURBAR)
    _, _, low = fourbar(LOW_FOURBAR)  # 31 degrees at its worst: below a 40-degree margin
    topology = analyze_topology(adjacency, node_types)
    target = as_target(fourbar_truth(low, 200)[4], False)
    args = (topology, low, 4, target, 200, 5, 40.0)
    with pytest.raises(ValueError, match="nearer a dead centre than its origin allows"):
        refine_validated(*args, origin=origin)
    assert refine_validated(*args).min_transmission_deg < 40  # alone, it is its own origin
    mirrored = origin.copy()
    (j, a, b) = topology.order[-1]
    gap = origin[b] - origin[a]
    normal = np.array([-gap[1], gap[0]]) / np.linalg.norm(gap)
    mirrored[j] -= 2 * np.dot(origin[j] - origin[a], normal) * normal  # across its parents' line
    with pytest.raises(ValueError, match="other branches than its origin"):
        refine_validated(topology, mirrored, 4, target, 200, 5, 3.0, origin=origin)


def test_margin_is_kept_when_the_best_fit_breaks_it() -> None:
    """Toward a four-bar whose transmission falls to 31 degrees, with a 40-degree margin: the
    result keeps 40 degrees and still comes closer."""
    adjacency, node_types, start = fourbar(GOOD_FOURBAR)
    _, _, low = fourbar(LOW_FOURBAR)
    order = analyze_topology(adjacency, node_types).order
    low_angle = math.degrees(
        math.asin(angle_sines(order, simulate(adjacency, node_types, low, 2000))[0].min())
    )
    start_angle = math.degrees(
        math.asin(angle_sines(order, simulate(adjacency, node_types, start, 2000))[0].min())
    )
    assert low_angle < 35 < 45 < start_angle
    target = fourbar_truth(low, 200)[4]
    result = refine(adjacency, node_types, start, 4, target, min_transmission_deg=40.0)
    assert result.chamfer_after < 0.8 * result.chamfer_before
    assert result.min_transmission_deg == pytest.approx(40.0, abs=0.5)  # the margin binds
    assert 40.0 <= result.min_transmission_deg
    assert_valid(adjacency, node_types, start, result.positions, 40.0)
    free = refine(adjacency, node_types, start, 4, target, min_transmission_deg=0.0)
    assert free.chamfer_after < result.chamfer_after


def test_steps_the_check_steps_refuse_are_undone(monkeypatch: pytest.MonkeyPatch) -> None:
    """Kept steps are checked at REFINE_CHECK_STEPS only every few (`FINE_EVERY`) and at the
    end. With no clearance and a turn of 16 steps, steps that keep the 40-degree margin at
    those steps dip below it between them: the check refuses them, refinement goes back to the
    last positions that passed, and what it returns keeps the margin at 2,000 steps."""
    adjacency, node_types, start = fourbar(GOOD_FOURBAR)
    _, _, low = fourbar(LOW_FOURBAR)
    target = fourbar_truth(low, 200)[4]
    refused = []

    def counted(*args: object) -> object:
        check = refine_checks.valid_trial(*args)
        refused.append(check is None)
        return check

    monkeypatch.setattr(refine_module, "valid_trial", counted)
    monkeypatch.setattr(refine_module, "CLEARANCE_DEG", 0.0)
    result = refine(adjacency, node_types, start, 4, target, min_transmission_deg=40.0, steps=16)
    assert_valid(adjacency, node_types, start, result.positions, 40.0)
    assert 40.0 <= result.min_transmission_deg
    assert result.chamfer_after < result.chamfer_before
    assert any(refused)  # the case this test is for


def test_random_mechanisms_never_get_worse_and_stay_valid() -> None:
    mechanisms = random_mechanisms(8, 8, 8, 14)
    rng = np.random.default_rng(9)
    improved = 0
    for adjacency, node_types, positions in mechanisms:
        joint = len(node_types) - 1
        # Toward the path of the same mechanism slightly moved: reachable, not trivially.
        moved = positions + rng.normal(0.0, 2e-3, positions.shape)
        try:
            target = simulate(adjacency, node_types, moved)[joint]
        except LockingError:
            continue
        result = refine(adjacency, node_types, positions, joint, target, iterations=40)
        truth = simulate(adjacency, node_types, result.positions)[joint]
        scale = chord(target)
        assert result.chamfer_after == pytest.approx(chamfer(target, truth) / scale, rel=1e-12)
        before = chamfer(target, simulate(adjacency, node_types, positions)[joint]) / scale
        assert result.chamfer_before == pytest.approx(before, rel=1e-12)
        assert result.chamfer_after <= result.chamfer_before
        improved += result.chamfer_after < 0.9 * result.chamfer_before
        assert_valid(adjacency, node_types, positions, result.positions, 3.0)
    assert improved >= 4


def test_no_iterations_changes_nothing() -> None:
    adjacency, node_types, positions = fourbar(GOOD_FOURBAR)
    target = fourbar_truth(positions, 200)[4] + 0.01
    result = refine(adjacency, node_types, positions, 4, target, iterations=0)
    np.testing.assert_array_equal(result.positions, positions)
    assert result.chamfer_after == result.chamfer_before
    assert result.iterations == 0


def test_a_deadline_already_passed_does_no_work() -> None:
    """Every iteration and every damping trial checks the deadline first: one already
    passed costs not a single trial, and the start is handed back as it was."""
    adjacency, node_types, positions = fourbar(GOOD_FOURBAR)
    topology = analyze_topology(adjacency, node_types)
    target = as_target(fourbar_truth(positions, 200)[4] + 0.01, False)
    late = refine_validated(
        topology, positions, 4, target, 200, 50, 3.0, deadline=time.perf_counter() - 1.0
    )
    assert late.evaluations == 0
    np.testing.assert_array_equal(late.positions, positions)
    assert late.chamfer_after == late.chamfer_before
    free = refine_validated(topology, positions, 4, target, 200, 50, 3.0)
    assert free.evaluations > 0 and free.chamfer_after < free.chamfer_before


# -- partial strokes ----------------------------------------------------------------------------


def overlap(a: tuple[int, int], b: tuple[int, int], steps: int) -> int:
    """Steps two cyclic runs (start, count) share."""
    first = {(a[0] + k) % steps for k in range(a[1])}
    return len(first & {(b[0] + k) % steps for k in range(b[1])})


@pytest.mark.parametrize("start", [0, 50, 170])
def test_partial_stroke_of_a_fourbar(start: int) -> None:
    """A third of the coupler curve (wrapping past step 0 for start 170)."""
    adjacency, node_types, positions = fourbar(GOOD_FOURBAR)
    curve = fourbar_truth(positions, 200)[4]
    true_run = (start, 67)
    stroke = curve[(start + np.arange(67)) % 200]
    exact = refine(adjacency, node_types, positions, 4, stroke, partial=True, iterations=0)
    assert exact.interval == true_run
    assert exact.chamfer_before < 1e-9
    moved = positions + np.random.default_rng(start).normal(0.0, 3e-3, positions.shape)
    result = refine(adjacency, node_types, moved, 4, stroke, partial=True)
    assert result.chamfer_after < 0.5 * result.chamfer_before
    assert overlap(result.interval, true_run, 200) >= 30
    # The reported chamfer is the stroke's to that run of the refined path, exactly.
    path = simulate(adjacency, node_types, result.positions)[4]
    run = path[(result.interval[0] + np.arange(result.interval[1])) % 200]
    assert result.chamfer_after == pytest.approx(chamfer(stroke, run) / chord(stroke), rel=1e-12)
    assert_valid(adjacency, node_types, moved, result.positions, 3.0)


def test_a_strokes_run_is_held_between_searches_and_exact_at_the_end(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Trials are measured on the run last found, which is searched again only every few kept
    steps (`RUN_EVERY`) or when no step gains on it; what refinement returns is still the
    best run of its path, even when the run it held to the end is not."""
    searches = []
    search = refine_checks.target_chamfer

    def counted(target: object, path: np.ndarray) -> tuple[float, tuple[int, int] | None]:
        searches.append(1)
        return search(target, path)  # type: ignore[arg-type]

    monkeypatch.setattr(refine_checks, "target_chamfer", counted)
    adjacency, node_types, positions = fourbar(GOOD_FOURBAR)
    curve = fourbar_truth(positions, 200)[4]
    # A stroke a little off the curve, so that refinement keeps many steps.
    stroke = 1.02 * curve[(40 + np.arange(90)) % 200] + 0.01
    moved = positions + np.random.default_rng(1).normal(0.0, 3e-3, positions.shape)
    first = refine(adjacency, node_types, moved, 4, stroke, partial=True, iterations=0).interval
    for every in (refine_module.RUN_EVERY, 10**6):
        monkeypatch.setattr(refine_module, "RUN_EVERY", every)
        searches.clear()
        result = refine(adjacency, node_types, moved, 4, stroke, partial=True, iterations=60)
        assert result.chamfer_after < 0.2 * result.chamfer_before
        assert 2 <= len(searches) <= result.evaluations // 2
        path = simulate(adjacency, node_types, result.positions)[4]
        start, count, _ = best_interval(path, stroke, MIN_POINTS)
        assert result.interval == (start, count) != first
        run = path[(start + np.arange(count)) % 200]
        assert result.chamfer_after == pytest.approx(
            chamfer(stroke, run) / chord(stroke), rel=1e-12
        )


def test_partial_stroke_of_random_mechanisms() -> None:
    for k, (adjacency, node_types, positions) in enumerate(random_mechanisms(12, 4, 8, 12)):
        joint = len(node_types) - 1
        path = simulate(adjacency, node_types, positions)[joint]
        start = 31 * k
        stroke = path[(start + np.arange(67)) % 200]
        result = refine(adjacency, node_types, positions, joint, stroke, partial=True, iterations=5)
        assert result.chamfer_after <= result.chamfer_before < 1e-9
        assert overlap(result.interval, (start, 67), 200) >= 60


# -- many candidates ----------------------------------------------------------------------------


def test_refine_many_equals_refine_and_reports_locks() -> None:
    adjacency, node_types, positions = fourbar(GOOD_FOURBAR)
    target = fourbar_truth(positions, 200)[4]
    start = positions + np.random.default_rng(0).normal(0.0, 1e-3, positions.shape)
    adjacency4, node_types4 = fourbar_topology(coupler=False)
    locking = np.array([[0.0, 0.0], [1.0, 0.0], [1.5, 0.2], [3.0, 0.0]])  # crank longest
    results = refine_many(
        [
            (adjacency, node_types, start, 4),
            (adjacency4, node_types4, locking, 2),
            (adjacency, node_types, positions, 2),
        ],
        target,
        iterations=50,
    )
    alone = refine(adjacency, node_types, start, 4, target, iterations=50)
    np.testing.assert_array_equal(results[0].positions, alone.positions)
    assert results[0].chamfer_after == alone.chamfer_after
    assert results[1].error is not None and "locks" in results[1].error
    np.testing.assert_array_equal(results[1].positions, locking)
    assert results[2].error is None and results[2].chamfer_after <= results[2].chamfer_before


# -- bad input ----------------------------------------------------------------------------------


def test_bad_input_raises_value_error() -> None:
    adjacency, node_types, positions = fourbar(GOOD_FOURBAR)
    target = fourbar_truth(positions, 200)[4]
    good = {"positions": positions, "joint": 4, "target_points": target}
    cases = [
        ({"joint": 0}, "joint 0 is fixed"),
        ({"joint": 5}, "joint must be from 0 to 4"),
        ({"joint": True}, "joint must be an integer"),
        ({"target_points": target[:2]}, "target_points must hold 3"),
        ({"target_points": np.full((5, 2), np.nan)}, "target_points must be finite"),
        ({"target_points": np.ones((5, 2))}, "target_points are all the same point"),
        ({"target_points": target[:, :1]}, r"target_points must be \[x, y\] pairs"),
        ({"positions": positions[:4]}, "positions must have shape"),
        ({"partial": "yes"}, "partial must be True or False"),
        ({"min_transmission_deg": MAX_TRANSMISSION_DEG + 1}, "min_transmission_deg must be from 0"),
        ({"min_transmission_deg": float("nan")}, "min_transmission_deg must be from 0"),
        ({"min_transmission_deg": "3"}, "min_transmission_deg must be a number"),
        ({"iterations": -1}, "iterations must be from 0"),
        ({"steps": MAX_REFINE_STEPS + 1}, f"at most {MAX_REFINE_STEPS} steps"),
        ({"steps": 2}, "steps must be >= 3"),
    ]
    for change, message in cases:
        with pytest.raises(ValueError, match=message):
            refine(adjacency, node_types, **{**good, **change})


def test_bad_mechanisms_raise_value_error() -> None:
    adjacency, node_types, positions = fourbar(GOOD_FOURBAR)
    target = fourbar_truth(positions, 200)[4]
    big = MAX_REFINE_JOINTS + 1
    adjacency_big, node_types_big = random_topology(0, n_joints=big)
    with pytest.raises(ValueError, match=f"at most {MAX_REFINE_JOINTS} joints"):
        refine(adjacency_big, node_types_big, np.zeros((big, 2)), big - 1, target)
    adjacency4, node_types4 = fourbar_topology(coupler=False)
    locking = np.array([[0.0, 0.0], [1.0, 0.0], [1.5, 0.2], [3.0, 0.0]])
    with pytest.raises(LockingError, match="locks"):
        refine(adjacency4, node_types4, locking, 2, target)
    with pytest.raises(ValueError, match="the crank has zero length"):
        refine(adjacency, node_types, np.zeros((5, 2)), 4, target)
    with pytest.raises(ValueError, match="candidate 1: joint 0 is fixed"):
        refine_many(
            [(adjacency, node_types, positions, 4), (adjacency, node_types, positions, 0)], target
        )
    with pytest.raises(ValueError, match="candidate 0 must be"):
        refine_many([(adjacency, node_types, positions)], target)


def _qp_by_enumeration(
    system: np.ndarray, gradient: np.ndarray, rows: np.ndarray, bounds: np.ndarray
) -> np.ndarray:
    """The minimizer of 1/2 d.system.d + gradient.d subject to rows.d >= bounds, found by
    trying every set of active constraints: the one whose equality solution is feasible with
    non-negative multipliers is the optimum (the problem is strictly convex)."""
    for size in range(len(rows) + 1):
        for active in itertools.combinations(range(len(rows)), size):
            on = list(active)
            n = len(gradient)
            kkt = np.zeros((n + size, n + size))
            kkt[:n, :n] = system
            kkt[:n, n:] = -rows[on].T
            kkt[n:, :n] = rows[on]
            solution = np.linalg.solve(kkt, np.concatenate([-gradient, bounds[on]]))
            delta, multipliers = solution[:n], solution[n:]
            if np.all(rows @ delta >= bounds - 1e-9) and np.all(multipliers >= -1e-9):
                return delta
    raise AssertionError("no active set is optimal")


def test_guarded_step_is_the_constrained_optimum() -> None:
    """The guarded step (the margin as linearized constraints) equals the optimum of the same
    quadratic program found by enumerating every active set, and keeps every constraint."""
    rng = np.random.default_rng(7)
    bound = 0
    for _ in range(200):
        n = int(rng.integers(2, 7))
        m = int(rng.integers(1, n + 1))  # guards are fewer than the coordinates they move
        half = rng.normal(size=(n, n))
        system = half @ half.T + 0.1 * np.eye(n)
        gradient = rng.normal(size=n)
        rows = rng.normal(size=(m, n))
        bounds = rng.normal(size=m) - 0.5
        expected = _qp_by_enumeration(system, gradient, rows, bounds)
        delta = guarded_minimum(system, gradient, rows, bounds)
        np.testing.assert_allclose(delta, expected, atol=1e-7)
        assert np.all(rows @ delta >= bounds - 1e-7)
        bound += not np.allclose(delta, np.linalg.solve(system, -gradient))
    assert bound > 50  # most draws have a binding constraint: the test exercises the guard


def test_a_guard_solve_that_overflows_refuses_the_step() -> None:
    """Guards whose system overflows (a nearly singular system, huge rows: met when a grown
    mechanism's new joint sat on its link) give no finite multiplier: the step is refused
    (None, so a more damped one is tried), where the active set used to raise numpy's
    ValueError out of `refine`."""
    from links_ray.engine.synthesis.refinement.step import guarded_step

    system = np.diag([1e-308, 1e-308])
    rows = np.array([[1e155, 1e155], [1e155, -1e155]])
    with np.errstate(all="ignore"):
        step = guarded_step(np.zeros((1, 2)), system, np.ones(2), (rows, np.ones(2)), 1.0)
    assert step is None


def test_nearest_pairs_equal_brute_force() -> None:
    """Each side's nearest point on the other, by the sorted sweep, equals comparing every pair
    (ties aside: random points have none)."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        path, drawn = rng.normal(size=(200, 2)), rng.normal(size=(int(rng.integers(3, 500)), 2))
        path_nn, path_d = np.empty(200, np.int64), np.empty(200)
        drawn_nn, drawn_d = np.empty(len(drawn), np.int64), np.empty(len(drawn))
        nearest_pairs(path, drawn, path_nn, path_d, drawn_nn, drawn_d)
        distances = np.linalg.norm(path[:, None] - drawn[None], axis=2)
        np.testing.assert_array_equal(path_nn, distances.argmin(axis=1))
        np.testing.assert_array_equal(drawn_nn, distances.argmin(axis=0))
        np.testing.assert_allclose(path_d, distances.min(axis=1), rtol=1e-15)
        np.testing.assert_allclose(drawn_d, distances.min(axis=0), rtol=1e-15)


def test_restore_raises_a_start_below_the_margin_to_it() -> None:
    """A four-bar at 31 degrees at its worst, refined toward its own curve with a 40-degree
    margin: as it was, it is done at once, below the margin (a dyad below it only keeps half
    its sine); restoring, it trades fit for angle until every dyad keeps the margin, measured
    afresh at 2,000 steps by the test's own geometry."""
    adjacency, node_types, positions = fourbar(LOW_FOURBAR)
    topology = analyze_topology(adjacency, node_types)
    target = as_target(fourbar_truth(positions, 200)[4], False)
    order = topology.order
    margin = math.sin(math.radians(40.0))

    def least_sine(refined: np.ndarray) -> float:
        traj = simulate(adjacency, node_types, refined, REFINE_CHECK_STEPS)
        return float(angle_sines(order, traj).min())

    assert least_sine(positions) < math.sin(math.radians(32.0))
    kept = refine_validated(topology, positions, 4, target, 200, 100, 40.0)
    assert kept.violation.kept  # not asked to restore: nothing is missed
    assert least_sine(kept.positions) < margin
    restored = refine_validated(topology, positions, 4, target, 200, 100, 40.0, restore=True)
    assert restored.violation.kept
    assert least_sine(restored.positions) >= margin - 1e-9
    assert restored.min_transmission_deg >= 40.0 - 1e-9
    assert restored.chamfer_after > 0.0  # the exact trace was given up for the margin
    assert_valid(adjacency, node_types, positions, restored.positions, 40.0)


def test_a_start_below_the_margin_is_missed_until_restored() -> None:
    """What a restoring refinement reports before it has had a step: the margin, missed."""
    adjacency, node_types, positions = fourbar(LOW_FOURBAR)
    topology = analyze_topology(adjacency, node_types)
    target = as_target(fourbar_truth(positions, 200)[4], False)
    missed = refine_validated(topology, positions, 4, target, 200, 0, 40.0, restore=True).violation
    assert not missed.kept
    assert missed.name == "min_transmission"
    assert 8.0 < missed.by < 10.0  # about 31 degrees against 40
