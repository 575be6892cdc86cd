"""The compiled solution path and structure rules (engine.kinematics.solution_path) give the answers
of their Python statements (engine.kinematics.mechanism) on every graph tried: grown topologies, and
the same graphs with links added, removed and moved, which break them in every way."""

from __future__ import annotations

import numpy as np
import pytest

from links_ray import random_topology
from links_ray.engine.inputs import InvalidMechanismError
from links_ray.engine.kinematics.mechanism import (
    Topology,
    _solution_path,
    analyze_topology,
    checked_topology,
    structure_violations,
)
from links_ray.engine.kinematics.solution_path import (
    obeys_structure,
    passes_graph_checks,
    solution_order,
)
from links_ray.engine.kinematics.topology import TOPOLOGY_RULES, grow_topology


def graphs(seed: int, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Grown topologies of both rules, each also with one to three links flipped and, now
    and then, a joint's kind changed."""
    rng = np.random.default_rng(seed)
    found = []
    for i in range(count):
        adjacency, node_types = random_topology(rng, rules=TOPOLOGY_RULES[i % len(TOPOLOGY_RULES)])
        found.append((adjacency, node_types))
        adjacency, node_types = adjacency.copy(), node_types.copy()
        n = len(node_types)
        for _ in range(rng.integers(1, 4)):
            a, b = rng.choice(n, 2, replace=False)
            adjacency[a, b] = adjacency[b, a] = 1 - adjacency[a, b]
        if rng.random() < 0.3:
            node_types[rng.integers(2, n)] = rng.integers(0, 2)
        found.append((adjacency, node_types))
    return found


def test_the_compiled_path_is_the_python_path() -> None:
    solved = refused = 0
    for adjacency, node_types in graphs(seed=1, count=600):
        compiled = solution_order(adjacency, node_types)
        try:
            expected = _solution_path(adjacency, node_types)
        except InvalidMechanismError:
            assert compiled is None
            refused += 1
            continue
        assert compiled is not None and compiled.dtype == np.int64
        assert np.array_equal(compiled, expected)
        solved += 1
    assert solved > 300 and refused > 100  # both ways are tried, often


def broken_forms(seed: int, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Grown topologies broken in the graph's form, the crank or the ground: an entry of 2 or
    256, a one-way link, a self-link, a kind out of range, a second actuated joint, a fixed
    crank tip, a ground link, the crank tip grounded twice, a cut crank; in several dtypes."""
    rng = np.random.default_rng(seed)
    found = []
    for i in range(count):
        adjacency, node_types = random_topology(rng)
        adjacency, node_types = adjacency.astype(np.int64), node_types.astype(np.int64)
        n = len(node_types)
        a, b = (int(x) for x in rng.choice(n, 2, replace=False))
        fixed = np.flatnonzero(node_types == 0)
        kind = i % 10
        if kind == 0:
            adjacency[a, b] = adjacency[b, a] = 2 if i % 20 else 256
        elif kind == 1:
            adjacency[a, b] = 1 - adjacency[a, b]
        elif kind == 2:
            adjacency[a, a] = 1
        elif kind == 3:
            node_types[a] = 3 if i % 20 else -1
        elif kind == 4:
            node_types[max(a, 2)] = 2
        elif kind == 5:
            node_types[1] = 0
        elif kind == 6 and len(fixed) > 1:
            adjacency[fixed[0], fixed[1]] = adjacency[fixed[1], fixed[0]] = 1
        elif kind == 7 and len(fixed) > 1:
            adjacency[1, fixed[1]] = adjacency[fixed[1], 1] = 1
        elif kind == 8:
            adjacency[0, 1] = adjacency[1, 0] = 0
        dtype = (np.int64, np.uint8, np.int16, np.int8)[i % 4]
        found.append((adjacency.astype(dtype), node_types.astype(dtype)))
    return found


def test_the_compiled_topology_checks_are_the_python_checks() -> None:
    """`analyze_topology`'s compiled way gives `checked_topology`'s answer, or none, on every
    graph; a graph it does not take, the Python statements refuse."""
    passed = refused = 0
    for adjacency, node_types in graphs(seed=4, count=300) + broken_forms(seed=5, count=400):
        try:
            expected = checked_topology(adjacency, node_types)
        except InvalidMechanismError:
            with pytest.raises(InvalidMechanismError):
                analyze_topology(adjacency, node_types)
            refused += 1
            continue
        assert passes_graph_checks(adjacency, node_types)
        got = analyze_topology(adjacency, node_types)
        for name in ("adjacency", "node_types", "order"):
            ours, theirs = getattr(got, name), getattr(expected, name)
            assert ours.dtype == theirs.dtype and np.array_equal(ours, theirs), name
        passed += 1
    assert passed > 250 and refused > 350


def test_the_compiled_structure_rules_are_the_python_rules() -> None:
    kept = broken = 0
    for adjacency, node_types in graphs(seed=2, count=600):
        try:
            topology = analyze_topology(adjacency, node_types)
        except InvalidMechanismError:
            continue
        problems = structure_violations(topology)
        assert obeys_structure(topology.adjacency, topology.node_types, topology.order) == (
            not problems
        )
        kept, broken = kept + (not problems), broken + bool(problems)
    assert kept > 300 and broken > 5


@pytest.mark.parametrize("rules", TOPOLOGY_RULES)
def test_a_grown_topology_is_the_analysed_one(rules: str) -> None:
    rng = np.random.default_rng(3)
    for n in list(range(5, 21)) * 20:
        grown = grow_topology(rng, n, rules)
        analysed = analyze_topology(grown.adjacency, grown.node_types)
        assert isinstance(grown, Topology) and np.array_equal(grown.order, analysed.order)
        assert grown.adjacency.dtype == np.uint8 and grown.node_types.dtype == np.int8
        assert structure_violations(grown) == []


def test_bad_buffers_are_refused_by_name() -> None:
    adjacency, node_types = random_topology(0)
    with pytest.raises(ValueError, match="adjacency must be a uint8 array of shape"):
        solution_order(adjacency.astype(np.int64), node_types)
    with pytest.raises(ValueError, match="node_types must be an int8 array"):
        solution_order(adjacency, node_types.astype(np.float64))
    order = solution_order(adjacency, node_types)
    with pytest.raises(ValueError, match="order must hold joints of the"):
        obeys_structure(adjacency, node_types, order + len(node_types))
    with pytest.raises(ValueError, match=r"adjacency must be a uint8 array of shape \(5, 5\)"):
        obeys_structure(adjacency, node_types[:5], order)
    with pytest.raises(ValueError, match="at least the crank's 2 joints, got 1"):
        obeys_structure(adjacency[:1, :1], node_types[:1], order[:0])
