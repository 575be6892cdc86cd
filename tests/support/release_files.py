"""Release-format files written from the release's published facts, for import tests.

Independent of links-ray's exporter: each batch is one `pickle.dump` of a list, the dataset's
entries `[A bool (n, n), x0 float32 (n, 2), node_type bool (n,)]` with the motor joints 0 and
1, the simulations `[x_sol (n, 200, 2) float32 (or float64, as the release's numpy solver
makes them), j]` at the absolute crank angles linspace(0, 2 pi, 200) (joint 1 at
x0[0] + r (cos t, sin t)), solved here by circle intersections keeping each joint's side from
x0, and the curated `[curve, j, node]` entries.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np

ANGLES = np.linspace(0.0, 2.0 * np.pi, 200)


def release_simulation(
    adjacency: np.ndarray, x0: np.ndarray, fixed: np.ndarray, dtype: type = np.float32
) -> np.ndarray | None:
    """(n, 200, 2) positions at the release's angles in `dtype` (float32 as the published
    files hold them; float64 as the release's numpy solver makes them), or None if a joint
    cannot be placed at some angle. Joints are placed as soon as two placed neighbours are
    known."""
    x0 = x0.astype(np.float64)
    n = len(x0)
    out = np.full((n, 200, 2), np.nan)
    radius = np.hypot(*(x0[1] - x0[0]))
    for k in np.flatnonzero(fixed):
        out[k] = x0[k]
    out[1] = x0[0] + radius * np.stack([np.cos(ANGLES), np.sin(ANGLES)], axis=1)
    known = set(np.flatnonzero(fixed).tolist()) | {1}
    while len(known) < n:
        for joint in range(n):
            if joint in known:
                continue
            parents = [p for p in np.flatnonzero(adjacency[joint]) if p in known]
            if len(parents) >= 2:
                a, b = sorted(parents)[:2]
                break
        else:
            return None
        r1 = np.hypot(*(x0[joint] - x0[a]))
        r2 = np.hypot(*(x0[joint] - x0[b]))
        u, v = x0[b] - x0[a], x0[joint] - x0[a]
        start = u[0] * v[1] - u[1] * v[0]
        pa, pb = out[a], out[b]
        gap = pb - pa
        d = np.hypot(gap[:, 0], gap[:, 1])
        along = (d * d + r1 * r1 - r2 * r2) / (2 * d)
        height_sq = r1 * r1 - along * along
        if np.any(height_sq < 0) or np.any(d == 0):
            return None
        unit = gap / d[:, None]
        normal = np.stack([-unit[:, 1], unit[:, 0]], axis=1)
        side = 1.0 if start >= 0 else -1.0
        out[joint] = pa + along[:, None] * unit + side * np.sqrt(height_sq)[:, None] * normal
        known.add(joint)
    return out.astype(dtype)


def write_release(
    folder: Path,
    batches: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]],
    curated: list[list[tuple[int, int]]] | None = None,
    generator_name: str | None = None,
    protocol: int = pickle.HIGHEST_PROTOCOL,
    dtype: type = np.float32,
) -> dict:
    """Write `batches` of (A, x0, node_type) as the release's dataset and simulation files, and
    the curated (j, node) pairs of each batch when given (with zero curves: the import keeps
    membership only); trajectories and curves in `dtype`. Returns how many mechanisms each
    batch's simulation file holds."""
    folder.mkdir(parents=True, exist_ok=True)
    names = (
        (generator_name, f"Solutions_{generator_name}", f"Curated_Normalized_{generator_name}")
        if generator_name
        else ("dataset", "simulation_dataset", "curated_dataset")
    )
    simulated = []
    with open(folder / names[0], "wb") as data, open(folder / names[1], "wb") as sims:
        for batch in batches:
            pickle.dump([list(entry) for entry in batch], data, protocol=protocol)
            solutions = []
            for j, (a, x0, fixed) in enumerate(batch):
                x_sol = release_simulation(a, x0, fixed, dtype)
                if x_sol is not None:
                    solutions.append([x_sol, j])
            pickle.dump(solutions, sims, protocol=protocol)
            simulated.append(len(solutions))
    if curated is not None:
        with open(folder / names[2], "wb") as out:
            for pairs in curated:
                curves = [[np.zeros((200, 2), dtype), j, node] for j, node in pairs]
                pickle.dump(curves, out, protocol=protocol)
    return {"simulated": simulated}


def as_release(adjacency: np.ndarray, node_types: np.ndarray, positions: np.ndarray) -> tuple:
    """A links-ray mechanism (FIXED 0, SIMPLE 1, ACTUATED 2) as the release's entry."""
    return (
        np.asarray(adjacency).astype(bool),
        np.asarray(positions).astype(np.float32),
        np.asarray(node_types) == 0,
    )
