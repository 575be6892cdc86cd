"""A refinement step's kernels (engine.synthesis.refinement.step_kernels) against their definitions:
every pair compared, finite differences of the chamfer, and each dyad's minima found one by one.
(The guarded step's optimum is checked against every active set in test_refine.)"""

from __future__ import annotations

import numpy as np

from links_ray.engine.synthesis.refinement.step_kernels import (
    chamfer_system,
    guard_minima,
    guarded_minimum,
)


def _pairs_system(
    path: np.ndarray,
    drawn: np.ndarray,
    jac: np.ndarray,
    rows: np.ndarray,
    floor: float,
    relative: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The IRLS system as its definition says, pair by pair: each path step of the run with
    its nearest drawn point, each drawn point with its nearest step of the run, both found by
    comparing every pair; weight 1 / (side's count x distance, at least the floor)."""
    run = path[rows]
    distances = np.linalg.norm(run[:, None] - drawn[None], axis=2)
    least = max(floor, relative * (distances.min(axis=1).mean() + distances.min(axis=0).mean()))
    pairs = [(i, int(distances[i].argmin()), len(rows)) for i in range(len(rows))]
    pairs += [(int(distances[:, k].argmin()), k, len(drawn)) for k in range(len(drawn))]
    cols = jac.shape[2]
    system, gradient = np.zeros((cols, cols)), np.zeros(cols)
    for i, k, count in pairs:
        weight = 1.0 / (count * max(distances[i, k], least))
        derivative = jac[rows[i]]  # (2, cols)
        system += weight * derivative.T @ derivative
        gradient += weight * derivative.T @ (run[i] - drawn[k])
    return system, gradient


def test_chamfer_system_is_the_sum_over_its_pairs() -> None:
    """Over the whole turn and over cyclic runs (one past the last step), for drawings of few
    and many points and for the weight floor binding or not."""
    rng = np.random.default_rng(11)
    for trial in range(30):
        steps, cols = int(rng.integers(3, 120)), 2 * int(rng.integers(2, 20))
        path = rng.normal(size=(steps, 2))
        drawn = rng.normal(size=(int(rng.integers(1, 300)), 2))
        jac = rng.normal(size=(steps, 2, cols))
        if trial % 3 == 0:
            interval = None
            rows = np.arange(steps)
        else:
            first, count = int(rng.integers(0, steps)), int(rng.integers(1, steps + 1))
            interval = (first, count)
            rows = (first + np.arange(count)) % steps
        floor, relative = (1e-3, 0.25) if trial % 2 else (0.5, 0.0)
        system, gradient = chamfer_system(path, drawn, jac, interval, floor, relative)
        want_system, want_gradient = _pairs_system(path, drawn, jac, rows, floor, relative)
        np.testing.assert_allclose(system, want_system, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(gradient, want_gradient, rtol=1e-10, atol=1e-12)
        np.testing.assert_array_equal(system, system.T)


def test_chamfer_gradient_is_the_chamfers_derivative() -> None:
    """With no weight floor the system's gradient is the derivative of the chamfer (mean
    nearest distance each way) itself: central finite differences of a path that moves
    linearly in its coordinates, where no nearest pair changes within the difference."""
    rng = np.random.default_rng(5)
    steps, cols = 60, 8
    base = rng.normal(size=(steps, 2))
    jac = rng.normal(size=(steps, 2, cols))
    drawn = rng.normal(size=(45, 2))

    def chamfer_at(theta: np.ndarray) -> float:
        path = base + jac @ theta
        distances = np.linalg.norm(path[:, None] - drawn[None], axis=2)
        return float(distances.min(axis=1).mean() + distances.min(axis=0).mean())

    _, gradient = chamfer_system(base, drawn, jac, None, 1e-300, 0.0)
    h = 1e-7
    numeric = np.array([(chamfer_at(h * e) - chamfer_at(-h * e)) / (2 * h) for e in np.eye(cols)])
    np.testing.assert_allclose(gradient, numeric, rtol=1e-5, atol=1e-8)


def test_guard_minima_are_each_dyads_low_steps_near_its_floor() -> None:
    """One row per step that is no higher than either neighbour (the first and last steps
    are neighbours) and within twice the clearance of its dyad's floor, by dyad, then step;
    its bound keeps the step the clearance above the floor."""
    rng = np.random.default_rng(2)
    for _ in range(40):
        dyads, steps, cols = int(rng.integers(0, 5)), int(rng.integers(1, 30)), 6
        trans = np.round(rng.uniform(0.0, 1.0, (dyads, steps)), 1)  # ties and plateaus
        dtrans = rng.normal(size=(dyads, steps, cols))
        floors = rng.uniform(0.0, 0.6, dyads)
        clearance = 0.05
        want_rows, want_bounds = [], []
        for d in range(dyads):
            for s in range(steps):
                value = trans[d, s]
                low = value <= trans[d, s - 1] and value <= trans[d, (s + 1) % steps]
                if low and value < floors[d] + 2 * clearance:
                    want_rows.append(dtrans[d, s])
                    want_bounds.append(floors[d] + clearance - value)
        rows, bounds = guard_minima(trans, dtrans, floors, clearance)
        assert rows.shape == (len(want_rows), cols)
        np.testing.assert_array_equal(rows, np.reshape(want_rows, (-1, cols)))
        np.testing.assert_array_equal(bounds, want_bounds)


def test_guarded_minimum_without_guards_is_the_newton_step() -> None:
    """No guards: the solution of system d = -gradient; a system that is not positive
    definite has no Cholesky factor: None, for the caller to damp it more."""
    rng = np.random.default_rng(9)
    half = rng.normal(size=(7, 7))
    system = half @ half.T + 0.01 * np.eye(7)
    gradient = rng.normal(size=7)
    delta = guarded_minimum(system, gradient, np.empty((0, 7)), np.empty(0))
    assert delta is not None
    np.testing.assert_allclose(system @ delta, -gradient, atol=1e-9)
    indefinite = np.diag([1.0, -1.0, 2.0])
    assert guarded_minimum(indefinite, np.ones(3), np.empty((0, 3)), np.empty(0)) is None
