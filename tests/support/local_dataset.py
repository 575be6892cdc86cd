"""A dataset generated and curated in this process, without Ray: the engine's tests read it.

The rows are those of `links generate` and `links curate` with the same plan and seed: each
generation shard is `data.generation.write_shard` (what a generator actor runs), and each
curation shard is `data.curation.curate_shard` (what a curator actor runs), committed with the
same markers. Only the scheduling (Ray's actors) and the leases are left out.
tests/cluster/test_local_dataset.py checks that Ray's run gives these rows.
"""

from __future__ import annotations

from links_ray.data.commit import committed_shards
from links_ray.data.curation import curate_shard
from links_ray.data.generation import GenerationPlan, write_shard
from links_ray.data.schemas import CURATION_TABLES
from links_ray.data.store import META, Store


def generate_and_curate(
    root: str,
    plan: GenerationPlan,
    curation_seed: int = 0,
    curation_tables: tuple[str, ...] = CURATION_TABLES,
    path_store: str = "points",
) -> str:
    """Write `plan`'s shards and their curation (`curation_tables`, stored as `path_store`)
    into `root` (a folder or store URI); returns `root`. Shards the root holds already are
    kept, as a resumed `links generate` and `links curate` keep them: a plan extended from the
    root's (`GenerationPlan.extended_to`) adds its new shards only."""
    store = Store.open(root)
    store.write_json(f"{META}/run.json", plan.config())
    generated = committed_shards(store, "shards")
    for shard in plan.shards():
        if shard.shard_id not in generated:
            write_shard(store, plan, shard)
    curated = committed_shards(store, "curation")
    for shard_id, marker in sorted(committed_shards(store, "shards").items()):
        if shard_id in curated:
            continue
        files = marker["files"]
        curate_shard(
            store,
            shard_id,
            marker["n_joints"],
            files["mechanisms"],
            files.get("simulations"),
            curation_seed,
            curation_tables,
            plan.steps,
            path_store=path_store,
        )
    return root


def stored_and_lean(folder: str, **plan: int) -> tuple[str, str]:
    """One plan (`GenerationPlan`'s keywords) written twice under `folder`: as "stored", with
    every table and the path tables with their points, and as "lean", mechanisms alone and the
    curated set as ids (`links curate --store ids`); their roots."""
    stored = generate_and_curate(f"{folder}/stored", GenerationPlan(**plan))
    lean = generate_and_curate(
        f"{folder}/lean",
        GenerationPlan(**plan, tables=("mechanisms",)),
        curation_tables=("curated",),
        path_store="ids",
    )
    return stored, lean
