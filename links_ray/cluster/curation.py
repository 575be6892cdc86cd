"""The curation pass on Ray Data: committed mechanisms become `paths` and `curated` tables.

The unit of work is a generation shard: its mechanisms and simulations files hold the same
mechanisms, so a shard is curated on its own, streamed through a Ray Data pipeline of curator
actors, and committed like generation shards (hidden files, then a marker under
``ROOT/_links/curation/``). A shard generated without its simulations is simulated again by its
curator, which gives the same rows. Rows depend only on the data and `--seed`, so reruns give
the same rows; a rerun curates only the shards not yet curated, including ones generated since.
"""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Callable, Iterable

import numpy as np
import ray
from ray.util.annotations import RayDeprecationWarning

from links_ray.cluster.connect import connect
from links_ray.cluster.progress import Progress
from links_ray.data.commit import committed_shards, remove_uncommitted
from links_ray.data.curation import KEEP_SHARE, curate_shard, path_shares
from links_ray.data.lease import Lease, LeaseLost, holder_still
from links_ray.data.schemas import CURATION_TABLES, check_path_store, choose_tables
from links_ray.data.store import META, Store, StoreError, diagnose, refuse_imported
from links_ray.engine.inputs import DEFAULT_STEPS

CURATION_FORMAT = 1
#: Passes a run makes when curators are lost (a worker killed, a node gone): each curates
#: only the shards the passes before it left, as a rerun of the command would.
CURATION_PASSES = 3


class ShardCurator:
    """A Ray Data actor: curates the generation shards it is given, one per row."""

    def __init__(
        self,
        uri: str,
        seed: int,
        lease_token: str,
        tables: tuple[str, ...],
        steps: int,
        path_store: str = "points",
    ) -> None:
        self.store = Store.open(uri, attempts=10)
        self.seed = seed
        self.lease_token = lease_token
        self.tables = tables
        self.steps = steps
        self.path_store = path_store

    def __call__(self, batch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Curate each shard of the batch; a shard the store refused reports its error as data
        (Ray Data would carry the exception as text only), so the driver can say it in a line."""
        paths, mechanisms, errors = [], [], []
        for shard, n, mechanisms_file, simulations_file in zip(
            batch["shard"],
            batch["n_joints"],
            batch["mechanisms_file"],
            batch["simulations_file"],
            strict=True,
        ):
            try:
                marker = self.curate(
                    int(shard), int(n), str(mechanisms_file), str(simulations_file)
                )
            except OSError as exc:
                paths.append(0)
                mechanisms.append(0)
                errors.append(f"shard {int(shard)}: {diagnose(exc)}")
                continue
            paths.append(marker["stats"]["paths"])
            mechanisms.append(marker["stats"]["mechanisms"])
            errors.append("")
        return {
            "shard": batch["shard"],
            "paths": np.array(paths),
            "mechanisms": np.array(mechanisms),
            "error": np.array(errors, dtype=object),
        }

    def curate(
        self, shard_id: int, n_joints: int, mechanisms_file: str, simulations_file: str
    ) -> dict:
        """Write one shard's chosen tables, then its marker, while this run holds the root;
        returns the marker (`data.curation.curate_shard`)."""

        def still_holder() -> None:
            if not holder_still(self.store, "writer", self.lease_token):
                raise LeaseLost(f"{self.store.uri}: the run this curator works for lost the root")

        return curate_shard(
            self.store,
            shard_id,
            n_joints,
            mechanisms_file,
            simulations_file,
            self.seed,
            self.tables,
            self.steps,
            before_commit=still_holder,
            path_store=self.path_store,
        )


def curate(
    root: str,
    seed: int = 0,
    workers: int | None = None,
    address: str | None = None,
    progress: bool = True,
    tables: str | Iterable[str] | None = None,
    starting: Callable[[], None] | None = None,
    path_store: str = "points",
) -> dict:
    """Curate every committed generation shard at `root` not curated yet; returns the summary.

    `tables` are the tables written: `paths`, `curated` or both (names, or one comma-separated
    string; default both, or with `path_store` "ids" the curated set alone). `path_store`
    "ids" writes them as ids and flags without points, a lean root whose readers derive the
    points (`links_ray.data.derived`). `starting` is called just before Ray starts, only when
    there is work.
    """
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    check_path_store(path_store)
    if tables is None:
        tables = ("curated",) if path_store == "ids" else CURATION_TABLES
    tables = choose_tables(tables, CURATION_TABLES)
    store = Store.open(root)
    with Lease.acquire(store, "writer", "links curate") as lease:
        summary = _curate_holding(
            store, lease, seed, tables, workers, address, progress, starting, path_store
        )
    return summary


def _curate_holding(
    store: Store,
    lease: Lease,
    seed: int,
    tables: tuple[str, ...],
    workers: int | None,
    address: str | None,
    progress: bool,
    starting: Callable[[], None] | None = None,
    path_store: str = "points",
) -> dict:
    """`curate`'s work, done while holding the root's writer lease."""
    run = refuse_imported(store)
    generated = committed_shards(store, "shards")
    if not generated:
        raise StoreError(f"{store.uri} holds no generated shards: run links generate first")
    settings = {
        "seed": seed,
        "keep_share": KEEP_SHARE,
        "format": CURATION_FORMAT,
        "tables": list(tables),
        "path_store": path_store,
    }
    # A pass recorded before tables or the store could be chosen wrote both, with points.
    defaults = {"tables": list(CURATION_TABLES), "path_store": "points"}
    store.claim(f"{META}/curation.json", settings, defaults=defaults)
    steps = run.get("steps", DEFAULT_STEPS)  # of shards to simulate again
    curated = committed_shards(store, "curation")
    remove_uncommitted(store, "curation", curated)
    todo = [marker for shard, marker in sorted(generated.items()) if shard not in curated]

    start = time.perf_counter()
    curated_now = len(todo)
    if todo:
        if starting is not None:
            starting()
        connect(address)
        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = False  # ours counts mechanisms, not blocks
        total = sum(m["stats"]["mechanisms"] for m in generated.values())
        done = sum(m["stats"]["mechanisms"] for m in curated.values())
        meter = Progress(total=total, done=done, unit="mechanisms", enabled=progress)
        try:
            for passes in range(1, CURATION_PASSES + 1):
                try:
                    _curate_shards(
                        store, lease, todo, seed, tables, steps, workers, meter, path_store
                    )
                    break
                except ray.exceptions.RayActorError as exc:
                    if passes == CURATION_PASSES:
                        lost = str(exc).splitlines()[0]
                        raise StoreError(
                            f"curation stopped: {CURATION_PASSES} passes each lost a curator "
                            f"({lost}); the same command finishes the pass"
                        ) from None
                    curated = committed_shards(store, "curation")
                    remove_uncommitted(store, "curation", curated)
                    todo = [m for shard, m in sorted(generated.items()) if shard not in curated]
                    if not todo:  # the lost curator had committed its shards
                        break
        finally:
            meter.close()
        lease.confirm()
        remove_uncommitted(store, "curation", committed_shards(store, "curation"))
    summary = summarize_curation(store, time.perf_counter() - start, curated_now, tables)
    summary["path_store"] = path_store
    store.write_json(f"{META}/curation_summary.json", summary)
    return summary


def _curate_shards(
    store: Store,
    lease: Lease,
    todo: list[dict],
    seed: int,
    tables: tuple[str, ...],
    steps: int,
    workers: int | None,
    meter: Progress,
    path_store: str = "points",
) -> None:
    """One Ray Data pass of `ShardCurator` actors over the generation shards of `todo` (their
    markers), each committed as it is done; RayActorError if a curator is lost, StoreError
    (after the pass) if the store refused a shard."""
    cpus = int(ray.cluster_resources().get("CPU", 1))
    actors = max(1, min(workers or cpus, cpus, len(todo)))
    shards = ray.data.from_items(
        [
            {
                "shard": m["shard"],
                "n_joints": m["n_joints"],
                "mechanisms_file": m["files"]["mechanisms"],
                "simulations_file": m["files"].get("simulations", ""),
            }
            for m in todo
        ],
        override_num_blocks=len(todo),
    )
    with warnings.catch_warnings():
        # Ray 2.60 takes `max_restarts` for Ray Data's actors only among its deprecated
        # `ray_remote_args`, and says so on stderr.
        warnings.filterwarnings("ignore", "`ray_remote_args` is deprecated", RayDeprecationWarning)
        results = shards.map_batches(
            ShardCurator,
            fn_constructor_kwargs={
                "uri": store.uri,
                "seed": seed,
                "lease_token": lease.token,
                "tables": tables,
                "steps": steps,
                "path_store": path_store,
            },
            batch_size=1,
            compute=ray.data.ActorPoolStrategy(size=actors),
            num_cpus=1,
            # Ray Data hands its actors their callable and its context through the object
            # store, and Ray cannot promise to restart an actor whose arguments are there (it
            # says so on stderr whenever restarts are allowed). A lost curator ends the pass
            # instead, and `curate` makes another over the shards left.
            max_restarts=0,
        )
    data_log = logging.getLogger("ray.data")
    level = data_log.level
    data_log.setLevel(logging.WARNING)  # Ray Data logs every stage; the meter says enough
    # ...and warns that its bars are off, which is this pass's choice, not the user's.
    bars_log = logging.getLogger("ray.data._internal.progress")
    bars_level = bars_log.level
    bars_log.setLevel(logging.ERROR)
    failed = ""
    try:
        for row in results.iter_rows():
            if row["error"]:
                failed = row["error"]
                break
            meter.advance(int(row["mechanisms"]))
    finally:
        data_log.setLevel(level)
        bars_log.setLevel(bars_level)
    if failed:
        raise StoreError(
            f"curation stopped: the store refused {failed}; once that is mended, the same "
            "command finishes the pass"
        )


def summarize_curation(
    store: Store, seconds: float, curated_now: int, tables: tuple[str, ...] = CURATION_TABLES
) -> dict:
    """Counts of paths (made, whether or not written), curated paths, arcs and circles, and the
    curated share, over all curated shards; `resimulated` counts the mechanisms simulated again."""
    markers = committed_shards(store, "curation")
    keys = ("mechanisms", "resimulated", "paths", "curated", "arcs", "circles", "both")
    totals = dict.fromkeys(keys, 0)
    compute_s = 0.0
    for marker in markers.values():
        for key in keys:
            # Markers written before curation could leave tables out count their rows only.
            totals[key] += marker["stats"].get(key, marker["rows"].get(key, 0))
        compute_s += marker["stats"]["seconds"]
    return {
        "out": store.uri,
        "tables": list(tables),
        "shards": len(markers),
        "shards_this_run": curated_now,
        **totals,
        "shares": path_shares(totals["paths"], totals["arcs"], totals["circles"], totals["both"]),
        "seconds": seconds,
        "mechanisms_per_core_second": totals["mechanisms"] / compute_s if compute_s else None,
    }
