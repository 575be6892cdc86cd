"""Adding a coupler point to a mechanism (engine.synthesis.coupler_points), against the
closed-form four-bar.

* A four-bar given a coupler point at its rocker tip B gets one mechanism a link of B: on the
  coupler A-B, the new joint traces Freudenstein's coupler curve of the point at (b, +-offset)
  in the coupler's frame; on the rocker O4-B, a circle about O4. The old joints trace what they
  traced.
* The new joint starts `offset` from the tracing joint, square to its link, away from the
  mechanism's centre.
* No coupler point past COUPLER_POINT_MAX_JOINTS; bad input is a ValueError naming it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import links_ray
from links_ray.engine.kinematics.mechanism import analyze_topology
from links_ray.engine.synthesis.coupler_points import COUPLER_POINT_MAX_JOINTS, with_coupler_point
from tests.engine.kinematics.test_solver import (
    fourbar_lengths,
    fourbar_positions,
    fourbar_topology,
    fourbar_truth,
)

STEPS = 360


def fourbar() -> tuple[object, np.ndarray]:
    """A crank-rocker's topology and positions (O2, A, B, O4), tracing B (joint 2)."""
    adjacency, node_types = fourbar_topology()
    positions = fourbar_positions((0.3, -0.2), 0.4, (0.25, 0.9, 0.7, 1.0), 1.1, 1)
    return analyze_topology(adjacency, node_types), positions


def test_a_four_bar_with_a_coupler_point_traces_the_closed_form_coupler_point() -> None:
    topology, positions = fourbar()
    offset = 0.05
    added = with_coupler_point(topology, positions, 2, offset)
    assert len(added) == 2  # B's links: the coupler (to A) and the rocker (to O4)
    parent = fourbar_truth(positions, STEPS)
    _, b, c, _ = fourbar_lengths(positions)
    for adjacency, node_types, at in added:
        assert adjacency.shape == (5, 5) and list(node_types) == [0, 2, 1, 0, 1]
        neighbour = next(int(k) for k in np.flatnonzero(adjacency[4]) if k != 2)
        assert np.count_nonzero(adjacency[4]) == 2
        # Square to the link, `offset` from B.
        step = at[4] - at[2]
        assert math.isclose(float(np.hypot(*step)), offset, rel_tol=1e-12)
        assert abs(float(step @ (at[2] - at[neighbour]))) < 1e-12
        paths = links_ray.simulate(adjacency, node_types, at, STEPS)
        np.testing.assert_allclose(paths[:4], parent, atol=1e-9)  # the old joints unmoved
        if neighbour == 1:  # on the coupler: Freudenstein's coupler point at (b, v)
            e = (at[2] - at[1]) / b
            v = float(step @ np.array([-e[1], e[0]]))
            assert math.isclose(abs(v), offset, rel_tol=1e-12)
            truth = fourbar_truth(at, STEPS)[4]
            np.testing.assert_allclose(paths[4], truth, atol=1e-9)
        else:  # on the rocker: a circle about O4
            assert neighbour == 3
            radius = np.hypot(*(paths[4] - at[3]).T)
            np.testing.assert_allclose(radius, math.hypot(c, offset), rtol=1e-9)
        # Away from the centre, so the triangle opens outward.
        assert step @ (at[2] - positions.mean(axis=0)) > 0


def test_coupler_points_again_and_again_stop_at_the_largest_mechanism() -> None:
    """Each coupler point traces in turn and is given one of its own: every mechanism is a valid
    topology that turns, until COUPLER_POINT_MAX_JOINTS."""
    topology, positions = fourbar()
    joint = 2
    while topology.n_joints < COUPLER_POINT_MAX_JOINTS:
        adjacency, node_types, positions = with_coupler_point(topology, positions, joint, 0.02)[0]
        topology = analyze_topology(adjacency, node_types)
        joint = topology.n_joints - 1
        assert links_ray.simulate(adjacency, node_types, positions, STEPS).shape[0] == joint + 1
    assert with_coupler_point(topology, positions, joint, 0.02) == []


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"offset": 0.0}, "offset must be positive"),
        ({"offset": math.nan}, "offset must be positive"),
        ({"joint": 4}, "joint must be in 0..3"),
        ({"positions": np.zeros((3, 2))}, r"positions must be \(4, 2\)"),
    ],
)
def test_a_bad_coupler_point_is_a_value_error(change: dict, message: str) -> None:
    topology, positions = fourbar()
    asked = {"positions": positions, "joint": 2, "offset": 0.05} | change
    with pytest.raises(ValueError, match=message):
        with_coupler_point(topology, asked["positions"], asked["joint"], asked["offset"])


def test_coupler_points_keep_the_joints_asked_for() -> None:
    """A synthesis asked for at most `max_joints` adds coupler points only up to them."""
    topology, positions = fourbar()
    assert with_coupler_point(topology, positions, 2, 0.05, max_joints=4) == []
    assert len(with_coupler_point(topology, positions, 2, 0.05, max_joints=5)) == 2
