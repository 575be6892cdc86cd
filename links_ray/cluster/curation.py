"""The curation pass on Ray Data: committed simulations become `paths` and `curated` tables.

The unit of work is a generation shard: its mechanisms and simulations files hold the same
mechanisms, so a shard is curated on its own, streamed through a Ray Data pipeline of curator
actors, and committed like generation shards (hidden files, then a marker under
``ROOT/_links/curation/``). Rows depend only on the data and `--seed`, so reruns give the same
rows; a rerun curates only the shards not yet curated, including ones generated since.
"""

from __future__ import annotations

import time

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import ray

from links_ray.cluster.connect import connect
from links_ray.cluster.progress import Progress
from links_ray.data.pathset import (
    KEEP_SHARE,
    arc_circle_counts,
    curated_mask,
    path_shares,
    path_table,
)
from links_ray.data.store import CURATION_TABLES, META, ShardWriter, Store, StoreError

CURATION_FORMAT = 1


class ShardCurator:
    """A Ray Data actor: curates the generation shards it is given, one per row."""

    def __init__(self, uri: str, seed: int) -> None:
        self.store = Store.open(uri, attempts=10)
        self.seed = seed

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        markers = [
            self.curate(int(shard), int(n), str(mechanisms), str(simulations))
            for shard, n, mechanisms, simulations in zip(
                batch["shard"],
                batch["n_joints"],
                batch["mechanisms_file"],
                batch["simulations_file"],
                strict=True,
            )
        ]
        return {
            "shard": batch["shard"],
            "paths": np.array([m["rows"]["paths"] for m in markers]),
            "mechanisms": np.array([m["stats"]["mechanisms"] for m in markers]),
        }

    def _read(self, relative: str) -> pa.Table:
        with self.store.fs.open_input_file(self.store.path(relative)) as source:
            return pq.read_table(source)

    def curate(
        self, shard_id: int, n_joints: int, mechanisms_file: str, simulations_file: str
    ) -> dict:
        """Write one shard's paths and curated paths, then its marker; returns the marker."""
        start = time.perf_counter()
        paths = path_table(self._read(mechanisms_file), self._read(simulations_file), n_joints)
        keep = curated_mask(paths, self.seed)
        writer = ShardWriter(self.store, shard_id, n_joints, stage="curation")
        try:
            for table, rows in (("paths", paths), ("curated", paths.filter(keep))):
                for batch in rows.to_batches(max_chunksize=50_000):
                    writer.write(table, batch)
            stats = {
                "mechanisms": len(np.unique(paths.column("mechanism_id").to_numpy())),
                **arc_circle_counts(paths),
                "seconds": time.perf_counter() - start,
            }
            return writer.commit(stats)
        except BaseException:
            writer.abort()
            raise


def curate(
    root: str,
    seed: int = 0,
    workers: int | None = None,
    address: str | None = None,
    progress: bool = True,
) -> dict:
    """Curate every committed generation shard at `root` not curated yet; returns the summary."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    store = Store.open(root)
    generated = store.committed_shards("shards")
    if not generated:
        raise StoreError(f"{store.uri} holds no generated shards: run links generate first")
    store.claim(
        f"{META}/curation.json", {"seed": seed, "keep_share": KEEP_SHARE, "format": CURATION_FORMAT}
    )
    curated = store.committed_shards("curation")
    todo = [marker for shard, marker in sorted(generated.items()) if shard not in curated]

    start = time.perf_counter()
    if todo:
        connect(address)
        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = False  # ours counts mechanisms, not blocks
        cpus = int(ray.cluster_resources().get("CPU", 1))
        actors = max(1, min(workers or cpus, cpus, len(todo)))
        shards = ray.data.from_items(
            [
                {
                    "shard": m["shard"],
                    "n_joints": m["n_joints"],
                    "mechanisms_file": m["files"]["mechanisms"],
                    "simulations_file": m["files"]["simulations"],
                }
                for m in todo
            ],
            override_num_blocks=len(todo),
        )
        results = shards.map_batches(
            ShardCurator,
            fn_constructor_kwargs={"uri": store.uri, "seed": seed},
            batch_size=1,
            concurrency=actors,
            num_cpus=1,
        )
        total = sum(m["stats"]["mechanisms"] for m in generated.values())
        done = sum(m["stats"]["mechanisms"] for m in curated.values())
        meter = Progress(total=total, done=done, unit="mechanisms", enabled=progress)
        try:
            for row in results.iter_rows():
                meter.advance(int(row["mechanisms"]))
        finally:
            meter.close()
        store.remove_uncommitted(CURATION_TABLES)
    summary = summarize_curation(store, time.perf_counter() - start, len(todo))
    store.write_json(f"{META}/curation_summary.json", summary)
    return summary


def summarize_curation(store: Store, seconds: float, curated_now: int) -> dict:
    """Counts of paths, arcs and circles, and the curated share, over all curated shards."""
    markers = store.committed_shards("curation")
    totals = {"mechanisms": 0, "paths": 0, "curated": 0, "arcs": 0, "circles": 0, "both": 0}
    compute_s = 0.0
    for marker in markers.values():
        totals["paths"] += marker["rows"].get("paths", 0)
        totals["curated"] += marker["rows"].get("curated", 0)
        for key in ("mechanisms", "arcs", "circles", "both"):
            totals[key] += marker["stats"][key]
        compute_s += marker["stats"]["seconds"]
    return {
        "out": store.uri,
        "shards": len(markers),
        "shards_this_run": curated_now,
        **totals,
        "shares": path_shares(totals["paths"], totals["arcs"], totals["circles"], totals["both"]),
        "seconds": seconds,
        "mechanisms_per_core_second": totals["mechanisms"] / compute_s if compute_s else None,
    }
