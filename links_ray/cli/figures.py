"""The dataset's figures as PNG (`links stats --plots DIR`); need matplotlib (extra `plots`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.dataset as pads

from links_ray.data.dataset import open_table
from links_ray.data.store import Store
from links_ray.engine.kinematics.solver import simulate


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise ValueError("figures need matplotlib: pip install 'links-ray[plots]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _sample(
    store: Store, table: str, columns: list[str] | None, count: int, rng: np.random.Generator
) -> list[dict]:
    """Up to `count` random rows of `table` (read from a few random files)."""
    dataset = open_table(store, table)
    fragments = list(dataset.get_fragments())
    picked = rng.choice(len(fragments), size=min(len(fragments), 4), replace=False)
    table_rows = pa.concat_tables(fragments[k].to_table(columns=columns) for k in picked)
    take = rng.choice(len(table_rows), size=min(count, len(table_rows)), replace=False)
    return table_rows.take(np.sort(take)).to_pylist()


def write_figures(root: str | Store, folder: str | Path, stats: dict, seed: int = 0) -> list[str]:
    """Write the figures for `stats` (from `dataset_stats`) into `folder`; returns their paths
    (candidates per valid's only when they were measured or recorded)."""
    plt = _pyplot()
    store = root if isinstance(root, Store) else Store.open(root, writable=False)
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    written = []

    candidates = stats["candidates_per_valid"]
    if candidates is not None:  # None when not measured: no figure of it
        sizes = sorted(int(n) for n in candidates)
        figure, axes = plt.subplots(figsize=(6, 4))
        axes.semilogy(sizes, [candidates[str(n)] for n in sizes], "o-")
        axes.axhline(500, color="grey", linestyle="--", label="paper: >500 on average")
        axes.set(xlabel="joints", ylabel="candidates per valid mechanism")
        axes.set_title("Infeasibility of random initial positions", fontsize=10)
        axes.legend()
        written.append(_save(figure, out / "candidates_per_valid.png", plt))

    mechanisms = stats["counts"]["mechanisms"]
    if mechanisms:
        by_size = mechanisms["by_joint_count"]
        figure, axes = plt.subplots(figsize=(6, 4))
        axes.bar([int(n) for n in by_size], list(by_size.values()))
        axes.set(xlabel="joints", ylabel="mechanisms", title="Joint counts")
        written.append(_save(figure, out / "joint_counts.png", plt))

    if stats["counts"]["paths"] and stats["counts"]["curated"]:
        figure, grids = plt.subplots(5, 10, figsize=(12, 6))
        for half, table in enumerate(("paths", "curated")):
            rows = _sample(store, table, ["points"], 25, rng)
            for k, row in enumerate(rows):
                axes = grids[k // 5, half * 5 + k % 5]
                points = np.asarray(row["points"]).reshape(-1, 2)
                axes.plot(points[:, 0], points[:, 1], linewidth=0.8)
        for axes in grids.ravel():
            axes.set(xlim=(0, 1), ylim=(0, 1), xticks=[], yticks=[], aspect="equal")
        figure.suptitle("Random normalized paths: before (left) and after (right) curation")
        written.append(_save(figure, out / "curation.png", plt))

    if mechanisms:
        rows = _sample(store, "mechanisms", None, 4, rng)
        traced = _trajectories(store, rows) if stats["counts"]["simulations"] else {}
        figure, grid = plt.subplots(1, len(rows), figsize=(4 * len(rows), 4))
        for axes, row in zip(np.atleast_1d(grid), rows, strict=True):
            _draw_mechanism(axes, row, traced.get(row["mechanism_id"]))
        written.append(_save(figure, out / "mechanisms.png", plt))
    return written


def _trajectories(store: Store, mechanisms: list[dict]) -> dict[int, list[float]]:
    """The stored trajectories of these mechanisms, by id."""
    ids = [row["mechanism_id"] for row in mechanisms]
    rows = open_table(store, "simulations").to_table(filter=pads.field("mechanism_id").isin(ids))
    return {row["mechanism_id"]: row["trajectories"] for row in rows.to_pylist()}


def _draw_mechanism(axes, mechanism: dict, trajectories: list[float] | None) -> None:
    """A mechanism with its joints' paths: stored ones, or simulated here when generation left
    the simulations out."""
    n = len(mechanism["node_types"])
    positions = np.asarray(mechanism["positions"]).reshape(n, 2)
    adjacency = np.asarray(mechanism["adjacency"]).reshape(n, n)
    types = np.asarray(mechanism["node_types"])
    if trajectories is None:
        paths = simulate(adjacency, types, positions)
    else:
        paths = np.asarray(trajectories).reshape(n, -1, 2)
    for joint in range(n):
        if types[joint] != 0:
            axes.plot(paths[joint, :, 0], paths[joint, :, 1], linewidth=0.7, alpha=0.7)
    for i, j in zip(*np.nonzero(np.triu(adjacency)), strict=True):
        axes.plot(*positions[[i, j]].T, color="black", linewidth=1.2)
    axes.scatter(*positions[types == 0].T, marker="^", color="black", zorder=3, label="fixed")
    axes.scatter(*positions[types != 0].T, color="white", edgecolor="black", zorder=3)
    axes.set(aspect="equal", xticks=[], yticks=[])
    axes.set_title(f"mechanism {mechanism['mechanism_id']} ({n} joints)", fontsize=9)


def _save(figure, path: Path, plt) -> str:
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return str(path)


def write_synthesis_figure(path: str | Path, curves: list[dict]) -> str:
    """One panel per synthesized curve (`links bench synthesize --figure`): the drawing, the
    path of the best retrieved mechanism, and the path the refined mechanism traces, framed on
    the drawing (the mechanism's links, at the crank's start, reach out of the frame). Each
    entry: `curve` (name), `points`, `retrieved_path`, `retrieved`, `refined` (chamfers) and
    `result` (the best synthesis result), and `partial` if the drawing is an open stroke."""
    plt = _pyplot()
    columns = 4
    rows = -(-len(curves) // columns)
    figure, grid = plt.subplots(rows, columns, figsize=(3.2 * columns, 3.2 * rows), squeeze=False)
    for axes, entry in zip(grid.flat, curves, strict=False):
        points = np.asarray(entry["points"])
        retrieved = np.asarray(entry["retrieved_path"])
        mechanism = entry["result"]["mechanism"]
        traced = np.asarray(entry["result"]["path"])
        positions = np.asarray(mechanism["positions"])
        adjacency = np.asarray(mechanism["adjacency"])
        fixed = np.asarray(mechanism["node_types"]) == 0
        drawing = points if entry.get("partial") else np.vstack([points, points[:1]])
        axes.plot(*drawing.T, color="0.75", linewidth=5, label="drawn")
        axes.plot(*retrieved.T, color="tab:orange", linewidth=1.2, label="retrieved")
        loop = np.vstack([traced, traced[:1]])
        axes.plot(*loop.T, color="tab:blue", linewidth=1.3, label="refined")
        for i, j in zip(*np.nonzero(np.triu(adjacency)), strict=True):
            axes.plot(*positions[[i, j]].T, color="black", linewidth=0.6, alpha=0.3)
        axes.scatter(*positions[fixed].T, marker="^", color="black", s=14, zorder=3)
        low, high = points.min(axis=0), points.max(axis=0)
        middle, half = (low + high) / 2, 0.65 * float((high - low).max())
        axes.set(aspect="equal", xticks=[], yticks=[])
        axes.set(
            xlim=(middle[0] - half, middle[0] + half), ylim=(middle[1] - half, middle[1] + half)
        )
        axes.set_title(
            f"{entry['curve'].replace('_', ' ')}: {entry['retrieved']:.4f} → "
            f"{entry['refined']:.4f} ({len(fixed)} joints)",
            fontsize=9,
        )
    for axes in list(grid.flat)[len(curves) :]:
        axes.axis("off")
    grid.flat[0].legend(fontsize=7, loc="lower left")
    return _save(figure, Path(path), plt)
