"""What a synthesis retrieves before it refines: how many paths, of which joint counts
(`retrievals`), and their answers joined (`pooled`), and what a retrieval answers
(`RetrievalResult`). The HTTP API plans its retrievals here too, so that a synthesis over HTTP
starts from the same candidates as one in Python.

Pure Python and numpy: no Ray.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, TypedDict

import numpy as np

from links_ray.engine.inputs import DEFAULT_K

__all__ = [
    "BELOW_FLOOR_CANDIDATES",
    "CANDIDATES",
    "PlacedMechanism",
    "RetrievalResult",
    "Retriever",
    "pooled",
    "retrievals",
]

#: Retrieved candidates the short pass refines.
CANDIDATES = 96
#: With a transmission floor, also BELOW_FLOOR_CANDIDATES paths retrieved whatever their
#: least transmission: refinement restores the floor first (`refine_validated`'s `restore`),
#: and among paths a floor leaves out are the best starts for shapes that few mechanisms
#: keeping it trace (curves that cross themselves).
BELOW_FLOOR_CANDIDATES = 48
#: A Pareto front also retrieves FRONT_CANDIDATES paths of at most each of these joint counts,
#: so that simple mechanisms are among the candidates even when complex ones match best.
FRONT_JOINTS, FRONT_CANDIDATES = (5, 6, 8), 24


class PlacedMechanism(TypedDict):
    """A retrieved path's reduced mechanism, placed in the drawing's frame."""

    adjacency: np.ndarray  # (n, n) uint8
    node_types: np.ndarray  # (n,) int8
    positions: np.ndarray  # (n, 2) float64


class RetrievalResult(TypedDict):
    """One retrieval result, as `RetrievalIndex.retrieve` answers it (docs/reference/contract.md
    says what each key means). A plain dict at run time, so results keep their documented keys;
    its arrays stay arrays from the index to synthesis (and across Ray Serve's handles), and
    become JSON lists only where an answer is written (the HTTP answers, the CLI's output)."""

    path_id: int
    mechanism_id: int
    joint: int
    chamfer: float
    min_transmission_deg: float | None
    n_joints: int
    points: np.ndarray  # (steps, 2) float64: the stored normalized path
    mechanism: PlacedMechanism
    mechanism_joint: int


class Retriever(Protocol):
    """What synthesis needs of a retrieval index."""

    def retrieve(
        self,
        points: object,
        k: int = DEFAULT_K,
        min_transmission: float = 0.0,
        max_joints: int | None = None,
    ) -> list[RetrievalResult]:
        """The k best retrieval results for the drawn `points`, best first, among the paths
        keeping `min_transmission` degrees whose reduced mechanisms have at most `max_joints`
        joints, each with its mechanism in the drawing's frame."""
        ...


def retrievals(
    k: int, max_joints: int | None, front: bool, min_transmission_deg: float
) -> list[tuple[int, int | None, float]]:
    """The retrievals a synthesis asks for, as (count, max_joints, min_transmission_deg):
    CANDIDATES (at least k) of at most `max_joints` joints keeping the floor
    `min_transmission_deg`; with a floor, BELOW_FLOOR_CANDIDATES more with none; for a Pareto
    `front` FRONT_CANDIDATES more of each smaller count of FRONT_JOINTS, keeping it. `pooled`
    joins their answers."""
    wanted: list[tuple[int, int | None, float]] = [
        (max(CANDIDATES, k), max_joints, min_transmission_deg)
    ]
    if min_transmission_deg > 0.0:
        wanted.append((BELOW_FLOOR_CANDIDATES, max_joints, 0.0))
    if front:
        wanted += [
            (FRONT_CANDIDATES, joints, min_transmission_deg)
            for joints in FRONT_JOINTS
            if max_joints is None or joints < max_joints
        ]
    return wanted


def pooled(answers: Sequence[Sequence[RetrievalResult]]) -> list[RetrievalResult]:
    """The results of several retrievals (`retrievals`), each path once, in their order."""
    seen: set[int] = set()
    results = []
    for answer in answers:
        for result in answer:
            if result["path_id"] not in seen:
                seen.add(result["path_id"])
                results.append(result)
    return results
