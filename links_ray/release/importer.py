"""Import of the LINKS release's own files into a links-ray root
(docs/guides/importing-the-release.md).

The release's files are read by `release.pickles`, one batch at a time, and one file's batch at
a time: a batch's mechanisms stay in memory while its simulations are grouped by joint count,
then its curated (j, node) pairs are read. Each batch is split by joint count into shards
(`release.import_shards.ShardPart`), each checked against the release's trajectories and
committed on its own by the commit protocol (`data.commit`) under the root's writer lease, so
an interrupted import resumes where it stopped and every shard is committed exactly once, under
ids that say where each row came from (`release.ids`):

    shard_id = SHARDS_PER_BATCH * release_batch + n_joints
    mechanism_id = BATCH_STRIDE * release_batch + release_index
    topology_id = mechanism_id // 5, variant = mechanism_id % 5   (the release's groups of 5)
    a negative's id = NEGATIVE_ID_BASE + mechanism_id

so `release_location(mechanism_id)` is the row's (release_batch, release_index). Joints keep
their release order; node types map to links-ray's: True (fixed) to FIXED (0), joint 1 to
ACTUATED (2), any other joint to SIMPLE (1). Positions are the release's float32 values as
float64, exactly.

Every mechanism is checked with links-ray's own validators and solver: at the release's angles
(`release.format.release_trajectories`' solver), compared with the release's own trajectories
where it has them; and over links-ray's own turn (DEFAULT_STEPS steps from the initial angle),
where one that locks goes to `negatives`. `paths` are links-ray's curation of the rest
(`pathset.trajectory_paths`); `curated` are the paths the release curated when it has
`curated_dataset`, else curation's seeded choice (`pathset.curated_mask`).

A pickled file can only be read from its start: a batch's length is known once it is read, so
no reader can seek to batch b without reading the batches before it. One reader
(`ReleaseParts`) therefore reads the files, in this process, and hands out the shards' parts;
they are imported here, one after another, or by a `runner` given them (`links import-release`
passes `cluster.release_import.import_on_ray`, which streams them to Ray actors through the
object store). The rows are the same either way.

Pure numpy/pyarrow: no Ray.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from links_ray.data.commit import committed_shards, remove_uncommitted
from links_ray.data.curation import KEEP_SHARE, path_shares
from links_ray.data.lease import Lease
from links_ray.data.schemas import CURATION_TABLES, GENERATION_TABLES
from links_ray.data.store import IMPORTED_SOURCE, META, Store
from links_ray.engine.inputs import DEFAULT_STEPS
from links_ray.release.checked_batch import AGREEMENT_TOLERANCE, CheckedBatch
from links_ray.release.ids import SHARDS_PER_BATCH
from links_ray.release.import_shards import ImportOptions, ShardPart, import_part
from links_ray.release.pickles import ReleaseFileError, read_batches, release_files

__all__ = ["ReleaseParts", "Runner", "import_release", "summarize_import"]

#: Disagreeing mechanisms named in the import summary (every shard's marker names all of its).
SHOWN_DISAGREEING = 100
IMPORT_FORMAT = 1
#: Called with "batch <b> committed" after each release batch's shards are all committed:
#: the fault tests' way to stop an import between batches (of an import in this process).
Failpoint = Callable[[str], None]
#: Imports one part and returns its markers: `import_part` with the run's options.
PartImport = Callable[[Store, ShardPart, Callable[[], None]], dict]
#: Imports every part of `ReleaseParts` at the store, under the lease, with the `PartImport`
#: given; returns the markers of the parts, and the most processes that imported at once.
Runner = Callable[[Store, Lease, "ReleaseParts", PartImport], tuple[list[dict], int]]


def _following(store: Store, relative: str | None) -> Iterator[tuple[int, int, Any]] | None:
    return None if relative is None else read_batches(store, relative)


def _next_batch(batches: Iterator[tuple[int, int, Any]], shown: str, batch: int) -> Any:
    found = next(batches, None)
    if found is None:
        raise ReleaseFileError(f"{shown} ends before batch {batch}, which dataset holds")
    return found[2]


class ReleaseParts:
    """The parts an import has left to do, read from the release's files at `source`
    (`release_files`), batch by batch: the shards neither stage has committed (`generated`,
    `curated`: the markers as the run found them) or only generation has.

    `total` is the release's mechanisms (valid or not) as far as they are known: None until the
    dataset file's second batch is read, then estimated from its size and the bytes read,
    exact (`exact`) once it is read to its end. `done` is the mechanisms of the shards that
    both stages had committed when the run began."""

    def __init__(
        self,
        source: Store,
        files: dict[str, str | None],
        generated: dict[int, dict],
        curated: dict[int, dict],
    ) -> None:
        self.source = source
        self.files = files
        self.generated = generated
        self.curated = curated
        self.total: int | None = None
        self.exact = False
        self.done = sum(
            marker["stats"]["mechanisms"] + marker["stats"]["negatives"]
            for shard, marker in generated.items()
            if shard in curated
        )

    def batches(self) -> Iterator[tuple[int, list[ShardPart]]]:
        """(release batch, its parts left to do) of each batch of the release, in order;
        ReleaseFileError in one line at the first batch that cannot be read (the parts of the
        batches before it have been handed out)."""
        source, files = self.source, self.files
        data_file = files["dataset"]
        sims_file, curated_file = files["simulation_dataset"], files["curated_dataset"]
        sims_shown = f"{source.uri}/{sims_file}"
        sims = _following(source, sims_file)
        chosen = _following(source, curated_file)
        shown = f"{source.uri}/{data_file}"
        size = source.fs.get_file_info(source.path(data_file)).size
        read = 0  # the mechanisms of the batches read so far
        for number, offset, value in read_batches(source, data_file):
            if offset:
                self.total = round(read * size / offset)
            batch = CheckedBatch(shown, number, value)
            del value
            read += batch.size
            shards = [
                (n, SHARDS_PER_BATCH * number + n) for n in np.unique(batch.n_joints).tolist()
            ]
            pending = [
                (n, i) for n, i in shards if i not in self.generated or i not in self.curated
            ]
            # One file's batch in memory at a time: each is reduced to what the parts keep
            # (trajectories by joint count, curated pairs) before the next is read. A batch an
            # earlier run committed is read only to reach the next.
            grouped = None
            if sims is not None:
                solutions = _next_batch(sims, sims_shown, number)
                if pending:
                    grouped = batch.solutions_by_joints(sims_shown, solutions)
                del solutions
            if chosen is not None:
                batch.add_curated(
                    f"{source.uri}/{curated_file}",
                    _next_batch(chosen, f"{source.uri}/{curated_file}", number),
                )
            parts = [
                ShardPart(
                    shard_id=shard_id,
                    n_joints=n,
                    batch=batch.part(n),
                    shown=shown,
                    solutions=None if grouped is None else grouped.get(n, []),
                    solutions_shown=sims_shown,
                    generated=self.generated.get(shard_id),
                )
                for n, shard_id in pending
            ]
            del batch, grouped
            yield number, parts
        self.total, self.exact = read, True

    def __iter__(self) -> Iterator[ShardPart]:
        """Every part left to do, batch by batch (`batches`)."""
        for _, parts in self.batches():
            yield from parts


def _import_here(
    store: Store,
    lease: Lease,
    parts: ReleaseParts,
    work: PartImport,
    failpoint: Failpoint | None,
) -> list[dict]:
    """Import every part in this process, batch by batch; returns their markers."""
    done = []
    for number, batch_parts in parts.batches():
        # A batch's trajectories are all checked before any of its shards commits.
        for part in batch_parts:
            part.check_solutions()
        for part in batch_parts:
            done.append(work(store, part, lease.confirm))
        del batch_parts
        if failpoint is not None:
            failpoint(f"batch {number} committed")
    return done


def import_release(
    src: str,
    out: str,
    seed: int = 0,
    failpoint: Failpoint | None = None,
    tables: str | Iterable[str] | None = None,
    path_store: str = "points",
    runner: Runner | None = None,
) -> dict:
    """Import the LINKS release's files at `src` (a folder or s3://) into the root `out`;
    returns the import summary (also saved as `_links/import_summary.json`).

    `seed` draws the curated set when the release has no `curated_dataset`. `tables` are the
    tables written, of mechanisms, negatives, paths and curated (names, or one comma-separated
    string; default all four, or with `path_store` "ids" mechanisms and curated); `path_store`
    "ids" writes the path tables as ids and flags without points, a lean root whose readers
    derive the points (`links_ray.data.derived`), as `links generate --tables mechanisms` then
    `links curate --store ids` leave one. The parts are imported in this process, or by
    `runner` (`Runner`). Resumable: the shards an earlier import of the same release with the
    same options committed are kept. Raises ValueError (ReleaseFileError, StoreError) in one
    line for a bad option or a file that cannot be read as the release writes it; the batches
    before the one at fault are committed.
    """
    options = ImportOptions.checked(seed, tables, path_store)
    source = Store.open(src, writable=False)
    files = release_files(source)
    if files["dataset"] is None:  # release_files refuses a folder without one
        raise ReleaseFileError(f"{source.uri} holds no release dataset")
    curated_from = "release" if files["curated_dataset"] is not None else "seed"
    store = Store.open(out)
    start = time.perf_counter()
    with Lease.acquire(store, "writer", "links import-release") as lease:
        store.claim(
            f"{META}/run.json",
            {
                "source": IMPORTED_SOURCE,
                "release": source.uri,
                "format": IMPORT_FORMAT,
                "steps": DEFAULT_STEPS,
                "tables": options.stage_tables(GENERATION_TABLES),
            },
        )
        store.claim(
            f"{META}/curation.json",
            {
                "seed": options.seed,
                "keep_share": KEEP_SHARE,
                "tables": options.stage_tables(CURATION_TABLES),
                "curated_from": curated_from,
                "path_store": options.path_store,
            },
            # An import recorded before the path tables' store could be chosen wrote points.
            defaults={"path_store": "points"},
        )
        generated = committed_shards(store, "shards")
        curated = committed_shards(store, "curation")
        remove_uncommitted(store, "shards", generated)
        remove_uncommitted(store, "curation", curated)
        parts = ReleaseParts(source, files, generated, curated)
        work = functools.partial(import_part, options=options)
        if runner is None:
            done, workers = _import_here(store, lease, parts, work, failpoint), 1
        else:
            done, workers = runner(store, lease, parts, work)
        lease.confirm()
        remove_uncommitted(store, "shards", committed_shards(store, "shards"))
        remove_uncommitted(store, "curation", committed_shards(store, "curation"))
        seconds = time.perf_counter() - start
        imported_now = sum(markers["curation"]["stats"]["mechanisms"] for markers in done)
        core_seconds = sum(markers["shards"]["stats"]["seconds"] for markers in done)
        summary = summarize_import(store, source.uri, curated_from, seconds, imported_now)
        summary.update(workers=workers, tables=list(options.tables), path_store=path_store)
        store.write_json(f"{META}/import_summary.json", summary)
        store.write_json(
            f"{META}/curation_summary.json",
            {
                "out": store.uri,
                "tables": options.stage_tables(CURATION_TABLES),
                "path_store": options.path_store,
                "shards": summary["shards"],
                "seconds": summary["seconds"],
                "mechanisms_per_core_second": (
                    imported_now / core_seconds if imported_now and core_seconds else None
                ),
                **{key: summary[key] for key in ("paths", "curated", "arcs", "circles", "both")},
                "shares": path_shares(
                    summary["paths"], summary["arcs"], summary["circles"], summary["both"]
                ),
            },
        )
    return summary


def summarize_import(
    store: Store, release: str, curated_from: str, seconds: float, imported_now: int
) -> dict:
    """The import summary, from the committed shards' markers: rows, the check against the
    release's trajectories, negatives, paths, and where the curated set came from; `seconds`
    and `mechanisms_per_second` are this run's, over the `imported_now` valid mechanisms it
    committed."""
    generated = committed_shards(store, "shards")
    curated = committed_shards(store, "curation")
    counts = (
        "mechanisms",
        "negatives",
        "topologies",
        "agreeing",
        "disagreeing",
        "locking_at_release_angles",
        "unchecked",
    )
    totals = {key: sum(m["stats"].get(key, 0) for m in generated.values()) for key in counts}
    path_counts = ("paths", "curated", "arcs", "circles", "both", "release_curated_unmatched")
    paths = {key: sum(m["stats"].get(key, 0) for m in curated.values()) for key in path_counts}
    disagreeing = sorted(i for m in generated.values() for i in m["stats"]["disagreeing_ids"])
    batches = {m["stats"]["release_batch"] for m in generated.values()}
    imported = totals["mechanisms"] + totals["negatives"]
    return {
        "out": store.uri,
        "release": release,
        "release_batches": len(batches),
        "shards": len(generated),
        **totals,
        "imported": imported,
        "worst_error": max((m["stats"]["worst_error"] for m in generated.values()), default=0.0),
        "agreement_tolerance": AGREEMENT_TOLERANCE,
        "disagreeing_ids": disagreeing[:SHOWN_DISAGREEING],
        **paths,
        "curated_from": curated_from,
        "seconds": seconds,
        "imported_this_run": imported_now,
        "mechanisms_per_second": imported_now / seconds if imported_now and seconds else None,
    }
