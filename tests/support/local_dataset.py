"""A dataset generated and curated in this process, without Ray: the engine's tests read it.

The rows are those of `links generate` and `links curate` with the same plan and seed: each
generation shard is `data.shards.write_shard` (what a generator actor runs), and each
curation shard is what `cluster.curation.ShardCurator.curate` does to it (`path_batches`, then
`curated_mask` with the curation seed), committed with the same `ShardWriter` and markers. Only
the scheduling (Ray's actors) and the leases are left out. tests/cluster/test_generation.py
checks that Ray's run gives these rows.
"""

from __future__ import annotations

import pyarrow as pa
import pyarrow.parquet as pq

from links_ray.data.commit import ShardWriter, committed_shards
from links_ray.data.pathset import curated_mask, path_batches
from links_ray.data.shards import GenerationPlan, write_shard
from links_ray.data.store import META, Store


def _read(store: Store, relative: str) -> pa.Table:
    with store.fs.open_input_file(store.path(relative)) as source:
        return pq.read_table(source)


def generate_and_curate(root: str, plan: GenerationPlan, curation_seed: int = 0) -> str:
    """Write `plan`'s shards and their curation into `root` (a folder or store URI); returns
    `root`."""
    store = Store.open(root)
    store.claim(f"{META}/run.json", plan.config())
    for shard in plan.shards():
        write_shard(store, plan, shard)
    for shard_id, marker in sorted(committed_shards(store, "shards").items()):
        n_joints = marker["n_joints"]
        mechanisms = _read(store, marker["files"]["mechanisms"])
        simulations_file = marker["files"].get("simulations")
        simulations = _read(store, simulations_file) if simulations_file else None
        writer = ShardWriter(store, shard_id, n_joints, stage="curation")
        counts = {"paths": 0, "curated": 0}
        for paths in path_batches(mechanisms, simulations, n_joints, plan.steps):
            curated = paths.filter(curated_mask(paths, curation_seed))
            for table, rows in (("paths", paths), ("curated", curated)):
                for batch in rows.to_batches(max_chunksize=50_000):
                    writer.write(table, batch)
            counts["paths"] += len(paths)
            counts["curated"] += len(curated)
        writer.commit({"mechanisms": len(mechanisms), **counts})
    return root
