"""The Pareto front of joint count against fit: the simplest mechanisms that still fit better.

Pure Python: no numpy of its own, no Ray.
"""

from __future__ import annotations

from collections.abc import Sequence

from links_ray.engine.synthesis.candidates import Candidate

__all__ = ["pareto_front"]


def pareto_front(candidates: Sequence[Candidate]) -> list[Candidate]:
    """The best candidate of each joint count that ranks better than every simpler one's, by
    joints ascending."""
    best: dict[int, Candidate] = {}
    for c in candidates:
        n = c.topology.n_joints
        if n not in best or c.rank() < best[n].rank():
            best[n] = c
    front: list[Candidate] = []
    for n in sorted(best):
        if not front or best[n].rank() < front[-1].rank():
            front.append(best[n])
    return front
