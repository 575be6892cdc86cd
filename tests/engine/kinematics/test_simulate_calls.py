"""`simulate` called one mechanism at a time: the topology cache and the fast positions check
(docs/reference/contract.md, Python API) change nothing that a call returns or raises.

Truth is independent of the cache: a fresh `TopologySimulator` (no cache), the plain-Python
solver (`engine.kinematics.reference`), closed-form four-bars that lock only between sampled steps
(`tests/support/fourbars.py`), and the full validators of `engine.inputs`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from links_ray import InvalidMechanismError, LockingError, TopologySimulator, simulate
from links_ray.engine.inputs import (
    MAX_COORDINATE,
    MIN_LINK_LENGTH,
    as_positions,
    as_steps,
    check_positions,
)
from links_ray.engine.kinematics.reference import simulate_reference
from links_ray.engine.kinematics.sampling import PositionSampler
from links_ray.engine.kinematics.solver import (
    _TopologyCache,
    simulate_batch,
    simulate_until_lock,
    topology_cache,
)
from links_ray.engine.kinematics.topology import random_topology
from tests.support.fourbars import stretched_four_bar, window_slack


def valid_mechanisms(count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """`count` valid mechanisms (8-20 joints) of distinct random topologies."""
    rng = np.random.default_rng(seed)
    found = []
    for _ in range(count):
        adjacency, node_types = random_topology(rng)
        sampler = PositionSampler(TopologySimulator(adjacency, node_types))
        found.append((adjacency, node_types, sampler.search(1, rng, "sequential").positions[0]))
    return found


def uncached(adjacency: object, node_types: object, positions: object, steps: int) -> np.ndarray:
    """The trajectories of a fresh simulator of the topology: no cache involved."""
    trajectories, valid = TopologySimulator(adjacency, node_types).simulate([positions], steps)
    assert valid[0]
    return trajectories[0]


def raised(call: Callable[..., object], *args: object) -> tuple[type, str] | None:
    """(type, message) of the ValueError `call(*args)` raises, or None."""
    try:
        call(*args)
    except ValueError as exc:
        return type(exc), str(exc)
    return None


def test_repeated_calls_equal_a_fresh_solve_and_the_reference() -> None:
    """Every call, the first (analysing the topology) and the later ones (from the cache),
    returns the trajectories of a fresh simulator bit for bit, and the plain-Python solver's
    to rounding; each topology is analysed once."""
    topology_cache.clear()
    mechanisms = valid_mechanisms(12, seed=5)
    for adjacency, node_types, positions in mechanisms:
        first = simulate(adjacency, node_types, positions, 90)
        analysed = topology_cache.simulator(adjacency, node_types)
        again = simulate(adjacency, node_types, positions, 90)
        assert topology_cache.simulator(adjacency, node_types) is analysed
        fresh = uncached(adjacency, node_types, positions, 90)
        assert np.array_equal(first, fresh) and np.array_equal(again, fresh)
        reference = np.array(simulate_reference(adjacency, node_types, positions, 90))
        np.testing.assert_allclose(again, reference, rtol=0, atol=1e-11)
    assert len(topology_cache) == len(mechanisms)


def test_plain_lists_and_other_dtypes_give_the_same_answer() -> None:
    """Lists, int8 and float arrays of one topology (each its own cache entry) and int or
    non-contiguous positions answer as the float64 arrays do."""
    adjacency, node_types, positions = valid_mechanisms(1, seed=8)[0]
    expected = uncached(adjacency, node_types, positions, 64)
    variants = [
        (adjacency.tolist(), node_types.tolist(), positions.tolist()),
        (adjacency.astype(np.int8), node_types.astype(np.int8), positions),
        (adjacency.astype(float), node_types.astype(float), np.asfortranarray(positions)),
        (adjacency.astype(bool), node_types, positions.astype(np.float32).astype(np.float64)),
    ]
    for adjacency_v, node_types_v, positions_v in variants[:3]:
        for _ in range(2):
            assert np.array_equal(simulate(adjacency_v, node_types_v, positions_v, 64), expected)
    # float32 positions round differently: compared with a fresh solve of those positions.
    adjacency_v, node_types_v, positions_v = variants[3]
    assert np.array_equal(
        simulate(adjacency_v, node_types_v, positions_v, 64),
        uncached(adjacency, node_types, positions_v, 64),
    )


def test_changing_the_callers_arrays_does_not_reach_the_cache() -> None:
    """The cache keeps copies: after a call, the caller's arrays changed in place describe
    another topology (here a broken one), and the next call answers for what they hold now;
    changed back, the first answer again. Changing a returned array changes no later one."""
    adjacency, node_types, positions = valid_mechanisms(1, seed=11)[0]
    expected = simulate(adjacency, node_types, positions)
    last = int(np.flatnonzero(adjacency[-1])[0])
    adjacency[-1, last] = adjacency[last, -1] = 0  # the last joint loses a parent
    refused = raised(lambda: TopologySimulator(adjacency, node_types))
    assert refused is not None and refused[0] is InvalidMechanismError
    for _ in range(2):
        assert raised(lambda: simulate(adjacency, node_types, positions)) == refused
    adjacency[-1, last] = adjacency[last, -1] = 1
    answer = simulate(adjacency, node_types, positions)
    assert np.array_equal(answer, expected)
    answer[:] = np.nan
    node_types_copy = node_types.copy()
    node_types[1] = 0  # no actuated joint: refused, and the cached topology is untouched
    assert raised(lambda: simulate(adjacency, node_types, positions))[0] is InvalidMechanismError
    assert np.array_equal(simulate(adjacency, node_types_copy, positions), expected)


BAD_TOPOLOGIES = [
    ([[0, 1], [1, 0]], [0, 1], "joint 1 must be the actuated joint"),
    ([[0, 1, 1], [1, 0, 1], [1, 1, 0]], [0, 2, 0], "joins two fixed joints"),
    ([[0, 1, 0], [1, 0, 1], [0, 1, 0]], [0, 2, 1], "more than one degree of freedom"),
    ([[0, 2], [2, 0]], [0, 2], "adjacency entries must be 0 or 1"),
    ([[0, 1], [0, 0]], [0, 2], "not symmetric"),
    ([[0, 1], [1, 0]], [0, 2, 1], "one entry per joint"),
    ([[0, 1], [1]], [0, 2], "not a rectangular array"),
    ([["a", "b"], ["c", "d"]], [0, 2], "must be numeric"),
]


@pytest.mark.parametrize(("adjacency", "node_types", "match"), BAD_TOPOLOGIES)
def test_a_bad_topology_raises_the_same_error_every_call(
    adjacency: list, node_types: list, match: str
) -> None:
    """A refused topology is never cached: each call raises what the analysis raises."""
    topology_cache.clear()
    positions = [[0.5, 0.5], [0.55, 0.5], [0.7, 0.6]][: len(node_types)]
    errors = [raised(lambda: simulate(adjacency, node_types, positions)) for _ in range(3)]
    assert errors[0] is not None and errors[0][0] is InvalidMechanismError
    assert match in errors[0][1]
    assert errors[1] == errors[0] and errors[2] == errors[0]
    assert len(topology_cache) == 0


def test_locking_is_raised_identically_between_steps_and_at_them() -> None:
    """A four-bar that locks only between two sampled steps (closed form) raises the same
    LockingError, at the step after its window, on every call; one with slack turns."""
    steps = 60
    locking = stretched_four_bar(17, steps, window_slack(steps))
    for _ in range(3):
        with pytest.raises(LockingError) as caught:
            simulate(locking["adjacency"], locking["node_types"], locking["positions"], steps)
        assert (caught.value.step, caught.value.node) == (18, 3)
    trajectories, step, node = simulate_until_lock(
        locking["adjacency"], locking["node_types"], locking["positions"], steps
    )
    assert (step, node) == (18, 3) and trajectories.shape == (4, 18, 2)
    turning = stretched_four_bar(17, steps, 1e-3)
    for _ in range(2):
        out = simulate(turning["adjacency"], turning["node_types"], turning["positions"], steps)
        assert np.array_equal(out, uncached(*turning.values(), steps))


def full_checks(topology_simulator: TopologySimulator, positions: object, steps: object) -> None:
    """What the validators of `engine.inputs` alone raise, in `simulate`'s order."""
    n = topology_simulator.n_joints
    array = as_positions(positions, n)
    as_steps(steps)
    check_positions(topology_simulator.topology.adjacency, array)


def test_positions_are_refused_exactly_as_the_full_checks_refuse_them() -> None:
    """Positions near every limit (coordinates about MAX_COORDINATE, links about
    MIN_LINK_LENGTH long, NaN, infinity, wrong shapes and types), alone and with a bad step
    count, raise what the full validators raise, or are simulated when they pass."""
    adjacency, node_types, positions = valid_mechanisms(1, seed=13)[0]
    simulator = TopologySimulator(adjacency, node_types)
    i, j = np.nonzero(np.triu(adjacency, 1))
    cases: list[object] = []
    for k in (0, len(i) // 2, len(i) - 1):  # the crank, a middle link, the last link
        for gap in (0.0, 0.4, 0.999999, 1.0, 1.000001, 1.5, 2.0, 2.1):
            moved = positions.copy()
            moved[j[k]] = moved[i[k]] + gap * MIN_LINK_LENGTH * np.array([0.6, 0.8])
            cases.append(moved)
    for value in (MAX_COORDINATE, np.nextafter(MAX_COORDINATE, np.inf), np.nan, np.inf, -np.inf):
        far = positions.copy()
        far[3, 1] = value
        cases.append(far)
    cases += [positions[:-1], positions.astype(np.float32), positions.tolist(), "xy", None]
    cases.append(np.stack([positions, positions])[:, :, 0])
    for case in cases:
        for steps in (50, 0, 1.5):
            expected = raised(full_checks, simulator, case, steps)
            got = raised(simulate, adjacency, node_types, case, steps)
            if expected is None:
                assert got is None or got[0] is LockingError
            else:
                assert got == expected, (case, steps)


def test_batch_entry_points_check_as_before() -> None:
    """`simulate_batch` and a prebuilt `TopologySimulator` check the steps first, then the
    positions' form and geometry, through the same fast check."""
    adjacency, node_types, positions = valid_mechanisms(1, seed=17)[0]
    bad = np.stack([positions, positions])
    bad[1, 2] = np.nan
    zero_link = np.stack([positions, positions])
    zero_link[1, 1] = zero_link[1, 0]
    simulator = TopologySimulator(adjacency, node_types)
    for call in (simulator.simulate, lambda p, s: simulate_batch(adjacency, node_types, p, s)):
        assert raised(call, bad, 0) == raised(as_steps, 0)
        assert "NaN or infinite" in raised(call, bad, 50)[1]
        assert "the crank has zero length" in raised(call, zero_link, 50)[1]
        trajectories, valid = call(np.stack([positions] * 3), 40)
        assert valid.all()
        assert np.array_equal(trajectories[2], uncached(adjacency, node_types, positions, 40))


def test_the_cache_is_bounded_and_drops_the_least_recently_used() -> None:
    """A cache of 3 keeps the 3 topologies used last; a dropped one is analysed again, to
    the same answer."""
    cache = _TopologyCache(3)
    mechanisms = valid_mechanisms(5, seed=19)
    simulators = [cache.simulator(a, t) for a, t, _ in mechanisms[:3]]
    assert cache.simulator(*mechanisms[0][:2]) is simulators[0]  # now the most recent
    cache.simulator(*mechanisms[3][:2])  # drops mechanism 1, the least recently used
    assert len(cache) == 3
    assert cache.simulator(*mechanisms[0][:2]) is simulators[0]
    again = cache.simulator(*mechanisms[1][:2])
    assert again is not simulators[1]
    assert np.array_equal(again.topology.order, simulators[1].topology.order)
    assert len(cache) == 3
