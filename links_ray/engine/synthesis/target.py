"""The drawing refinement aims at (`Target`), and the chamfer of a path against it.

Its own module so that the refinement step (`engine.synthesis.refinement.step`) and the loop that
takes the steps (`engine.synthesis.refinement.loop`) both name it without importing each other.

Pure numpy/numba: no Ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from links_ray.engine.inputs import MIN_POINTS, as_drawn_points
from links_ray.engine.kinematics.paths import chamfer, longest_chord
from links_ray.engine.synthesis.refinement.kernels import best_interval

__all__ = ["Target", "as_target", "run_chamfer", "target_chamfer", "timed_distances"]


@dataclass
class Target:
    """A validated drawing and its scale (`as_target` makes one).

    `points` (T, 2) float64: the drawn points. `chord`: the drawing's longest chord, in the
    drawing's units; refinement's chamfers are divided by it. `partial`: the points are an open
    stroke, matched to a run of a turn. `crank` (T, 2): for a timed target, the cos and sin of
    the crank angle (from the mechanism's start) at which each point is to be reached; its
    measure is then the timed error, not the chamfer (`target_error`).
    """

    points: np.ndarray
    chord: float
    partial: bool
    crank: np.ndarray | None = None

    def timed(self, angles: np.ndarray) -> Target:
        """This target with each point to be reached at `angles` (T,) radians of the crank
        from the mechanism's start."""
        crank = np.ascontiguousarray(np.stack([np.cos(angles), np.sin(angles)], axis=1))
        return Target(self.points, self.chord, self.partial, crank)


def as_target(points: object, partial: object) -> Target:
    """The drawing `points` ([x, y] pairs) as a `Target`. Raises ValueError naming bad points
    (as `target_points`) or a `partial` that is not a bool."""
    if not isinstance(partial, bool | np.bool_):
        raise ValueError(f"partial must be True or False, got {partial!r}")
    drawn = as_drawn_points(points, "target_points")
    i, j = longest_chord(drawn)
    return Target(drawn, float(np.hypot(*(drawn[j] - drawn[i]))), bool(partial))


def target_chamfer(target: Target, path: np.ndarray) -> tuple[float, tuple[int, int] | None]:
    """(chamfer, interval): the chamfer distance between the target's points and `path`
    (steps, 2), in the drawing's units (not yet divided by the chord), and for a partial
    target the matched run (start step, count) of the path, else None. For a partial target
    the chamfer is the least over the path's cyclic runs of at least MIN_POINTS steps."""
    if not target.partial:
        return chamfer(target.points, path), None
    start, count, _ = best_interval(path, target.points, MIN_POINTS)
    run = (int(start), int(count))
    # The exact chamfer of the chosen run, so accepted steps compare like with like.
    return run_chamfer(target, path, run), run


def run_chamfer(target: Target, path: np.ndarray, interval: tuple[int, int]) -> float:
    """The chamfer distance between the target's points and the run `interval` (start step,
    count) of `path` (steps, 2), cyclic, in the drawing's units: for a partial target, no less
    than `target_chamfer`'s, which is the least over every run."""
    start, count = interval
    return chamfer(target.points, path[(start + np.arange(count)) % len(path)])


def timed_distances(target: Target, timed_path: np.ndarray) -> np.ndarray:
    """(T,) distance of each drawn point from the path at its crank angle, `timed_path` (T, 2)
    (the path solved at the target's `crank`), in the drawing's units."""
    return np.hypot(*(timed_path - target.points).T)
