"""The shard commit protocol: what a reader sees is exactly what was committed.

A stage's unit of work is a shard. Generation writes three tables per shard, curation two::

    ROOT/mechanisms/n_joints=12/shard-000042-<attempt>.parquet   a shard's files, final names
    ROOT/_links/shards/shard-000042.json                         its generation marker
    ROOT/_links/curation/shard-000042.json                       its curation marker

Each try at a shard is an attempt with a random name of its own, and every file it writes carries
that name, so two attempts of one shard alive at once (a shard Ray redoes while the actor it gave
up on still writes) never touch each other's files. An attempt streams into hidden files
(``_shard-000042-<attempt>.parquet``). To commit, it closes and syncs them, moves each to its
final name, syncs their folders, and then creates the marker, which names the files and their
row counts. **The marker is the commit**, and it is created only if absent
(`Store.create_exclusive`), so exactly one attempt of a shard commits. Readers
(`committed_files`, and through it `load`, `open_table`, curation, stats, export and the
retrieval index) read only the files that markers name.

- An attempt that finds the marker there already has lost: it deletes its own files and
  returns the winner's marker (the shard is committed all the same, with the same rows).
- An attempt that fails aborts: it deletes its own files, unless the marker names them (it
  failed after committing).
- Cleanup (`remove_uncommitted`) deletes hidden files, and files no marker names of shards that
  a marker commits: those attempts can never commit. A moved file of a shard with no marker may
  be a live attempt's about to commit, so it stays until the shard is committed; after a
  finished run every shard is, and a plain read of a table sees exactly the committed rows.

A marker is never half there: an S3 object appears whole, and on a local disk it is a link to
a whole, synced file. One that cannot be read (damaged) counts as absent, and cleanup deletes
it so that its shard can be committed again. One that names a file outside the root
(`marker_path`) is refused: a root made to read what is not its own is no dataset.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import pyarrow as pa
import pyarrow.parquet as pq

from links_ray.data.schemas import (
    CURATION_TABLES,
    GENERATION_TABLES,
    ID_SCHEMAS,
    PARQUET_OPTIONS,
    SCHEMAS,
)
from links_ray.data.store import META, TEMPORARY_PREFIX, Store

#: Each stage's marker folder (under `ROOT/_links/`) and the tables its shards write.
STAGE_TABLES = {"shards": GENERATION_TABLES, "curation": CURATION_TABLES}
#: The stage whose markers commit each table's files.
TABLE_STAGE = {table: stage for stage, tables in STAGE_TABLES.items() for table in tables}
#: Markers read at once: a store answers many small reads in parallel far faster than in turn.
MARKER_READERS = 16
#: Age after which a protocol temporary (`_tmp-*`) is litter from a failed write, not one under way.
STALE_TEMPORARY_S = 3600.0

#: Called with the name of each step an attempt has just finished: in a commit "closed",
#: "moved <table>", then "marked" (it committed) or "lost" (another attempt had); in an abort
#: of an attempt that had moved files, "aborting" (the marker read, its files not yet deleted).
#: The fault tests' way to stop an attempt, or to interleave two, between any two steps. What
#: a failpoint raises at "aborting" is ignored: an abort never raises.
Failpoint = Callable[[str], None]

#: A shard file's name: hidden while written, the shard, the attempt (absent in roots written
#: before final names carried it), e.g. `shard-000042-9f0c4e1a2b3d5f67.parquet`.
SHARD_NAME = re.compile(r"(_?)shard-(\d{6,})(?:[-.]([0-9a-f]+))?\.parquet")


def shard_file(table: str, n_joints: int, shard_id: int, attempt: str) -> str:
    """The final path of an attempt's file of a shard, relative to the root."""
    return f"{table}/n_joints={n_joints}/shard-{shard_id:06d}-{attempt}.parquet"


def marker_file(shard_id: int, stage: str = "shards") -> str:
    """The path, relative to the root, of a shard's commit marker for `stage`."""
    return f"{META}/{stage}/shard-{shard_id:06d}.json"


def _marker_shard(name: str) -> int | None:
    """The shard id of a marker's file name (`shard-000042.json`), or None."""
    match = re.fullmatch(r"shard-(\d{6,})\.json", name)
    return int(match.group(1)) if match else None


def _marker_names(store: Store, stage: str) -> dict[int, str]:
    names = {}
    for relative in store.list_files(f"{META}/{stage}"):
        shard = _marker_shard(relative.rsplit("/", 1)[-1])
        if shard is not None:
            names[shard] = relative
    return names


def committed_shards(store: Store, stage: str = "shards") -> dict[int, dict]:
    """The markers of the shards `stage` committed, by shard id; unreadable ones are left out,
    and one naming a file outside the root is refused (`marker_path`'s ValueError)."""
    if stage not in STAGE_TABLES:
        raise ValueError(f"stage must be one of {', '.join(STAGE_TABLES)}, got {stage!r}")
    names = _marker_names(store, stage)
    with ThreadPoolExecutor(MARKER_READERS) as pool:
        markers = dict(zip(names, pool.map(store.read_json, names.values()), strict=True))
    committed = {
        shard: marker
        for shard, marker in sorted(markers.items())
        if _well_formed(marker, shard, STAGE_TABLES[stage])
    }
    for shard, marker in committed.items():
        _check_files(store, names[shard], marker)
    return committed


def marker_path(store: Store, marker: str, relative: str) -> str:
    """`relative`, a file the marker at `marker` names, if it is a file under the store's root:
    a relative path of plain names (no `..`, `.` or empty parts; no scheme or drive such as
    `s3://`, `file:` or `C:`; no backslash or NUL) that on a local disk resolves, symbolic
    links followed, inside the root. Else ValueError naming the marker and the path."""
    parts = relative.split("/")
    why = None
    if relative.startswith("/"):
        why = "an absolute path"
    elif ":" in relative:
        why = "a scheme or drive"
    elif "\\" in relative or "\0" in relative:
        why = "a backslash or NUL"
    elif any(part in ("", ".", "..") for part in parts):
        why = "a '..', '.' or empty part"
    elif store.is_local:
        root = os.path.realpath(store.root)
        if os.path.commonpath([root, os.path.realpath(store.path(relative))]) != root:
            why = "a path that resolves outside the root"
    if why is not None:
        shown = relative if len(relative) <= 200 else relative[:200] + "..."
        raise ValueError(
            f"{store.uri}: commit marker {marker} names {shown!r}, {why}: a marker may name "
            "only files under its root"
        )
    return relative


def _check_files(store: Store, marker: str, committed: dict) -> None:
    """Refuse `committed`, the marker at `marker`, if it names a file outside the root."""
    for relative in committed["files"].values():
        marker_path(store, marker, relative)


def _well_formed(marker: dict | None, shard: int, tables: tuple[str, ...]) -> bool:
    if marker is None or marker.get("shard") != shard:
        return False
    files, rows = marker.get("files"), marker.get("rows")
    return (
        isinstance(files, dict)
        and isinstance(rows, dict)
        and isinstance(marker.get("n_joints"), int)
        and isinstance(marker.get("stats"), dict)
        and all(table in tables and isinstance(path, str) for table, path in files.items())
    )


def committed_files(store: Store, table: str, markers: dict[int, dict] | None = None) -> list[str]:
    """The files (relative to the root) that commit markers name for `table`, in shard order.

    `markers` are the table's stage markers, read now when not given: pass the same markers to
    read several tables as of one moment.
    """
    if table not in TABLE_STAGE:
        raise ValueError(f"table must be one of {', '.join(TABLE_STAGE)}, got {table!r}")
    if markers is None:
        markers = committed_shards(store, TABLE_STAGE[table])
    return [marker["files"][table] for marker in markers.values() if table in marker["files"]]


def remove_uncommitted(store: Store, stage: str, markers: dict[int, dict]) -> int:
    """Delete what attempts of `stage` left that can never be committed; returns how many files.

    `markers` are the stage's markers as read before the call. Deleted: every hidden attempt
    file, every shard file that no marker names of a shard a marker commits (a losing or
    failed attempt's), markers that cannot be read, and the protocol's old temporaries. A
    moved file of a shard without a marker stays: its attempt may be alive and about to commit
    (then its marker names it); once another attempt commits the shard, it goes.

    No commit ever loses a file to this, whenever it runs. But an attempt whose hidden file it
    deletes fails, so a run calls it only while none of its own writers is at work: at its start,
    before they start, and at its end, after they have stopped.
    """
    removed = 0
    named = {relative for marker in markers.values() for relative in marker["files"].values()}
    for table in STAGE_TABLES[stage]:
        for relative in store.list_files(table):
            match = SHARD_NAME.fullmatch(relative.rsplit("/", 1)[-1])
            if match is None:
                continue  # not the protocol's: left alone
            hidden, shard = bool(match.group(1)), int(match.group(2))
            if hidden or (shard in markers and relative not in named):
                removed += store.delete(relative)
    for shard, relative in _marker_names(store, stage).items():
        # Read again: a marker may have been created since `markers` were read.
        if shard not in markers and not _well_formed(
            store.read_json(relative), shard, STAGE_TABLES[stage]
        ):
            removed += store.delete(relative)
    # A reader may be writing the index cache right now: only old temporaries are litter.
    stale = time.time() - STALE_TEMPORARY_S
    for relative, modified in store.list_files(META, with_times=True):
        if relative.rsplit("/", 1)[-1].startswith(TEMPORARY_PREFIX) and modified < stale:
            removed += store.delete(relative)
    return removed


class ShardWriter:
    """One attempt at a shard: streams its record batches into hidden files, then commits them
    together, or learns that another attempt of the shard committed first.

    Used as a context manager, anything raised inside the block aborts the attempt
    (`abort`) on its way up."""

    def __init__(
        self,
        store: Store,
        shard_id: int,
        n_joints: int,
        stage: str = "shards",
        failpoint: Failpoint | None = None,
    ) -> None:
        if stage not in STAGE_TABLES:
            raise ValueError(f"stage must be one of {', '.join(STAGE_TABLES)}, got {stage!r}")
        self.store = store
        self.shard_id = shard_id
        self.n_joints = n_joints
        self.stage = stage
        self.attempt = uuid.uuid4().hex[:16]
        self.rows: dict[str, int] = {}
        #: After `commit`: True if this attempt committed the shard, False if another had.
        self.won: bool | None = None
        self._failpoint = failpoint
        self._writers: dict[str, pq.ParquetWriter] = {}
        self._streams: dict[str, pa.NativeFile] = {}
        self._moved: list[str] = []

    def __enter__(self) -> ShardWriter:
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        if kind is not None:
            self.abort()

    @property
    def marker(self) -> str:
        """The path of this shard's commit marker, relative to the root."""
        return marker_file(self.shard_id, self.stage)

    def _final(self, table: str) -> str:
        return shard_file(table, self.n_joints, self.shard_id, self.attempt)

    def _temporary(self, table: str) -> str:
        folder, name = self._final(table).rsplit("/", 1)
        return f"{folder}/_{name}"

    def _step(self, name: str) -> None:
        if self._failpoint is not None:
            self._failpoint(name)

    def write(self, table: str, batch: pa.RecordBatch) -> None:
        """Append rows (with the table's schema) to the shard's file for `table`."""
        if table not in STAGE_TABLES[self.stage]:
            raise ValueError(f"the {self.stage} stage writes no {table} table")
        if table not in self._writers:
            # A path table may be stored as ids, without its points (data.derived).
            if batch.schema not in (SCHEMAS[table], ID_SCHEMAS.get(table)):
                raise ValueError(f"rows of {table} with columns {batch.schema.names}")
            relative = self._temporary(table)
            self.store._make_parent(relative)
            stream = self.store.fs.open_output_stream(self.store.path(relative))
            self._streams[table] = stream
            self._writers[table] = pq.ParquetWriter(stream, batch.schema, **PARQUET_OPTIONS)
        self._writers[table].write_batch(batch)
        self.rows[table] = self.rows.get(table, 0) + batch.num_rows

    def commit(self, stats: dict) -> dict:
        """Close and sync the files, move them to their final names, sync their folders, then
        create the marker (the commit). Returns the shard's marker: this attempt's, or, if
        another attempt committed the shard first (`won` is False), that one's, after deleting
        this attempt's files."""
        for table, writer in self._writers.items():
            writer.close()
            self._streams[table].close()
            self.store.sync_file(self._temporary(table))
        self._step("closed")
        files = {}
        for table in self._writers:
            final = self._final(table)
            self.store.fs.move(self.store.path(self._temporary(table)), self.store.path(final))
            self._moved.append(final)
            files[table] = final
            self._step(f"moved {table}")
        for folder in sorted({final.rsplit("/", 1)[0] for final in self._moved}):
            self.store.sync_folder(folder)
        marker = {
            "shard": self.shard_id,
            "n_joints": self.n_joints,
            "attempt": self.attempt,
            "files": files,
            "rows": self.rows,
            "stats": stats,
        }
        encoded = (json.dumps(marker, indent=1) + "\n").encode()
        if self.store.create_exclusive(self.marker, encoded) is not None:
            self.won = True
            self._step("marked")
            return marker
        committed = self.store.read_json(self.marker)
        if committed is not None and committed.get("attempt") == self.attempt:
            # This attempt's own marker: a retried create whose first try had succeeded.
            self.won = True
            self._step("marked")
            return committed
        self.won = False
        self._step("lost")
        self._delete_own()
        if not _well_formed(committed, self.shard_id, STAGE_TABLES[self.stage]):
            raise OSError(
                f"{self.store.uri}: another attempt holds {self.marker}, which cannot be "
                "read; the next run's cleanup deletes it and the shard is done again"
            )
        _check_files(self.store, self.marker, committed)  # type: ignore[arg-type]
        return committed

    def abort(self) -> None:
        """Delete this attempt's files, unless the shard's marker names them (the attempt
        failed after committing). Never raises: it runs while another error is on its way up,
        and what it cannot delete the next run's cleanup will."""
        for table, writer in self._writers.items():
            for close in (writer.close, self._streams[table].close):
                try:
                    close()
                except Exception:  # the error being handled is the one to report
                    pass
        for table in self._writers:
            self.store.delete(self._temporary(table))
        if not self._moved:
            return
        try:
            marker = self.store.read_json(self.marker)
        except Exception:  # unknown whether this attempt committed: its files stay
            return
        if marker is not None and marker.get("attempt") == self.attempt:
            return
        with contextlib.suppress(Exception):
            self._step("aborting")
        self._delete_own()

    def _delete_own(self) -> None:
        """Delete the files this attempt moved to their final names: no marker names them."""
        for final in self._moved:
            self.store.delete(final)
        self._moved.clear()
