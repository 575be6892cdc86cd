"""Placing retrieval results in the query's frame.

A match is found between normalized paths, in one of the query's four variants; a result's
mechanism is moved, turned, scaled and (if the match was mirrored) mirrored so that its joint
traces the path where the query was drawn.

No Ray.
"""

from __future__ import annotations

import numpy as np

from links_ray.engine.kinematics.paths import normalization
from links_ray.engine.kinematics.solver import simulate
from links_ray.search.query import variant_map


def into_query_frame(
    adjacency: np.ndarray,
    node_types: np.ndarray,
    positions: np.ndarray,
    joint: int,
    variant: int,
    query_matrix: np.ndarray,
    query_offset: np.ndarray,
) -> np.ndarray:
    """The positions (n, 2) of a mechanism moved, turned, scaled and (if the match was
    mirrored) mirrored so that `joint` traces its path where the query was drawn: `variant`
    is the query variant matched (`query.variant_map`), `query_matrix` and `query_offset` the
    query's normalization (`engine.kinematics.paths.normalization`). Raises `LockingError` if the
    mechanism does not turn."""
    traced = simulate(adjacency, node_types, positions)[joint]
    _, matrix, offset = normalization(traced)
    variant_matrix, variant_offset = variant_map(variant)
    normalized = positions @ matrix.T + offset  # the candidate's normalized frame
    as_query = normalized @ variant_matrix.T + variant_offset  # undo the query's variant
    return (as_query - query_offset) @ np.linalg.inv(query_matrix).T


def degrees_or_none(angle: np.floating) -> float | None:
    """An angle in degrees for JSON: None where the dataset stores none (NaN)."""
    return None if np.isnan(angle) else float(angle)
