"""The compiled solution path and structure rules (engine.solution_path) give the answers of
their Python statements (engine.mechanism) on every graph tried: grown topologies, and the
same graphs with links added, removed and moved, which break them in every way."""

from __future__ import annotations

import numpy as np
import pytest

from links_ray import random_topology
from links_ray.engine.inputs import InvalidMechanismError
from links_ray.engine.mechanism import (
    Topology,
    _solution_path,
    analyze_topology,
    structure_violations,
)
from links_ray.engine.solution_path import obeys_structure, solution_order
from links_ray.engine.topology import TOPOLOGY_RULES, grow_topology


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
