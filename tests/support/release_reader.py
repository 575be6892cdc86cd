"""A reader of the LINKS release's files written from its published facts alone, as code
written for the release reads them: numpy and pickle only, nothing of links-ray.

It reads each file's batches with an unpickler that allows numpy's array globals only,
simulates `[A, x0, node_type]` with the motor on joints [0, 1] by circle intersections at the
absolute crank angles linspace(0, 2 pi, 200), each dyad keeping its side from x0, and
normalizes a curve by the release's rule as its facts state it.
"""

from __future__ import annotations

import pickle
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


def normalize(curve: np.ndarray) -> np.ndarray:
    """The release's rule as its facts state it, one step at a time."""
    curve = curve.astype(np.float64)
    if not np.isfinite(curve).all():
        return np.zeros_like(curve)
    left, here = 0, int(np.argmax(np.sum((curve - curve[0]) ** 2, axis=1)))
    for _ in range(len(curve)):
        onward = int(np.argmax(np.sum((curve - curve[here]) ** 2, axis=1)))
        if onward == left:
            break
        left, here = here, onward
    dx, dy = curve[here] - curve[left]
    best = None
    for angle in (-np.arctan2(dy, dx), -np.arctan2(dy, dx) + np.pi):
        c, s = np.cos(angle), np.sin(angle)
        candidate = curve @ np.array([[c, s], [-s, c]])
        candidate -= candidate.min(axis=0)
        middle = np.argsort(np.abs(candidate[:, 0] - 0.5), kind="stable")[:5]
        height = candidate[middle, 1].mean()
        if best is None or height < best[0] - 1e-12:
            best = (height, candidate)
    return best[1] / best[1][:, 0].max()
