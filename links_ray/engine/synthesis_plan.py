"""What a synthesis retrieves before it refines: how many paths, of which joint counts
(`retrievals`), and their answers joined (`pooled`). The HTTP API plans its retrievals here
too, so that a synthesis over HTTP starts from the same candidates as one in Python.

Pure Python: no Ray.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from links_ray.engine.inputs import DEFAULT_K

__all__ = ["CANDIDATES", "Retriever", "pooled", "retrievals"]

#: Retrieved candidates the short pass refines.
CANDIDATES = 96
#: A Pareto front also retrieves FRONT_CANDIDATES paths of at most each of these joint counts,
#: so that simple mechanisms are among the candidates even when complex ones match best.
FRONT_JOINTS, FRONT_CANDIDATES = (5, 6, 8), 24


class Retriever(Protocol):
    """What synthesis needs of a retrieval index."""

    def retrieve(
        self,
        points: object,
        k: int = DEFAULT_K,
        min_transmission: float = 0.0,
        max_joints: int | None = None,
    ) -> list[dict]:
        """The k best retrieval results for the drawn `points`, best first, among the paths
        keeping `min_transmission` degrees whose reduced mechanisms have at most `max_joints`
        joints, each with its mechanism in the drawing's frame."""
        ...


def retrievals(k: int, max_joints: int | None, front: bool) -> list[tuple[int, int | None]]:
    """The retrievals a synthesis asks for, as (count, max_joints): CANDIDATES (at least k) of
    at most `max_joints` joints, and for a Pareto `front` FRONT_CANDIDATES more of each smaller
    count of FRONT_JOINTS; `pooled` joins their answers."""
    wanted: list[tuple[int, int | None]] = [(max(CANDIDATES, k), max_joints)]
    if front:
        wanted += [
            (FRONT_CANDIDATES, joints)
            for joints in FRONT_JOINTS
            if max_joints is None or joints < max_joints
        ]
    return wanted


def pooled(answers: Sequence[Sequence[dict]]) -> list[dict]:
    """The results of several retrievals (`retrievals`), each path once, in their order."""
    seen: set[int] = set()
    results = []
    for answer in answers:
        for result in answer:
            if result["path_id"] not in seen:
                seen.add(result["path_id"])
                results.append(result)
    return results
