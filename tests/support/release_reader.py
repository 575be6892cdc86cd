"""A reader of the LINKS release's files written from its published facts alone, as code
written for the release reads them: numpy and pickle only, nothing of links-ray.

It reads each file's batches with an unpickler that allows numpy's array globals only,
simulates `[A, x0, node_type]` with the motor on joints [0, 1] by circle intersections at the
absolute crank angles linspace(0, 2 pi, 200), each dyad keeping its side from x0, and
normalizes a curve by the release's rule as its facts state it (`normalize`: of the two half
turns, the one whose 5 points nearest x = 0.5 reach the lower highest y).
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from pathlib import Path

import numpy as np

#: The release's absolute crank angles.
ANGLES = np.linspace(0.0, 2.0 * np.pi, 200)


class ReleaseUnpickler(pickle.Unpickler):
    """What the release's files may name: numpy arrays, dtypes and scalars (numpy 1 and 2)."""

    ALLOWED = {
        (module, name)
        for core in ("numpy.core.multiarray", "numpy._core.multiarray")
        for module, name in ((core, "_reconstruct"), (core, "scalar"))
    } | {("numpy", "ndarray"), ("numpy", "dtype")}

    def find_class(self, module: str, name: str) -> object:
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"{module}.{name} is not allowed")
        return super().find_class(module, name)


def read_batches(path: Path) -> list[list]:
    batches = []
    with open(path, "rb") as stream:
        while True:
            try:
                batches.append(ReleaseUnpickler(stream).load())
            except EOFError:
                return batches


def simulate(a: np.ndarray, x0: np.ndarray, fixed: np.ndarray) -> np.ndarray | None:
    """(n, 200, 2) positions with motor [0, 1] at the absolute angles linspace(0, 2 pi, 200);
    None if some dyad cannot close."""
    x0 = x0.astype(np.float64)
    n = len(x0)
    out = np.zeros((n, 200, 2))
    known = fixed.copy()
    out[fixed] = x0[fixed][:, None, :]
    crank = np.linalg.norm(x0[1] - x0[0])
    out[1] = x0[0] + crank * np.stack([np.cos(ANGLES), np.sin(ANGLES)], axis=1)
    known[1] = True
    while not known.all():
        solvable = [j for j in np.flatnonzero(~known) if np.count_nonzero(a[j] & known) >= 2]
        assert solvable, "no joint has two placed neighbours"
        for j in solvable:
            p, q = np.flatnonzero(a[j] & known)[:2]
            r1, r2 = np.linalg.norm(x0[j] - x0[p]), np.linalg.norm(x0[j] - x0[q])
            start = x0[q] - x0[p]
            side = np.sign(start[0] * (x0[j] - x0[p])[1] - start[1] * (x0[j] - x0[p])[0])
            between = out[q] - out[p]
            d = np.linalg.norm(between, axis=1)
            along = (r1**2 - r2**2 + d**2) / (2 * d)
            h2 = r1**2 - along**2
            if np.any(h2 < 0):
                return None
            u = between / d[:, None]
            normal = np.stack([-u[:, 1], u[:, 0]], axis=1)
            out[j] = out[p] + along[:, None] * u + side * np.sqrt(h2)[:, None] * normal
            known[j] = True
    return out


def normalize(curve: np.ndarray, height: Callable[[np.ndarray], float] = np.max) -> np.ndarray:
    """The release's rule (its `get_oriented`) as its facts state it, one step at a time.

    Hop from point 0 to the point farthest from it, and on, until the farthest point from the
    current one is the one just left: the chord joins those two. Turn the curve by the angle,
    at most a quarter turn either way, that lays the chord along x, and also by that angle and
    a half turn more. Move each turned curve so its least x and least y are 0. Keep the half
    turn only if the highest y of its 5 points nearest x = 0.5 is lower than the first turn's
    (both in the curve's own units: nothing is scaled yet) by more than a millionth of the
    curve's width: the release compares them in float32, where a smaller difference is
    rounding's, and keeps the first on equal heights. Divide by the x extent. (`height=np.mean`
    is the rule links-ray once followed, kept so a test can show the two differ.) A curve
    that holds NaN, or has no extent, becomes zeros. The hops measure distances in the curve's
    own dtype, as the release's code does on its float32 curves; the turns are in float64.
    """
    if not np.isfinite(curve).all():
        return np.zeros(curve.shape)
    left, here = 0, int(np.argmax(np.linalg.norm(curve - curve[0], axis=1)))
    for _ in range(len(curve)):
        onward = int(np.argmax(np.linalg.norm(curve - curve[here], axis=1)))
        if onward == left:
            break
        left, here = here, onward
    points = curve.astype(np.float64)
    dx, dy = points[here] - points[left]
    quarter = np.pi / 2 if dx == 0 else float(np.arctan(dy / dx))
    turns = []
    for angle in (quarter, quarter + np.pi):
        c, s = np.cos(angle), np.sin(angle)
        candidate = points @ np.array([[c, -s], [s, c]])  # turned by -angle
        candidate -= candidate.min(axis=0)
        middle = np.argsort(np.abs(candidate[:, 0] - 0.5), kind="stable")[:5]
        turns.append((height(candidate[middle, 1]), candidate))
    (first_height, first), (second_height, second) = turns
    width = first[:, 0].max()
    kept = second if second_height < first_height - 1e-6 * width else first
    extent = kept[:, 0].max()
    if not extent > 0:
        return np.zeros(curve.shape)
    return kept / extent
