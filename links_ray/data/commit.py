"""The shard commit protocol: what a reader sees is exactly what was committed.

A stage's unit of work is a shard. Generation writes three tables per shard, curation two::

    ROOT/mechanisms/n_joints=12/shard-000042.parquet     the shard's files, final names
    ROOT/_links/shards/shard-000042.json                 its generation marker
    ROOT/_links/curation/shard-000042.json               its curation marker

A shard streams into hidden files (``_shard-000042.<attempt>.parquet``). To commit, the writer
closes them, moves each to its final name, and then writes the marker, which names the files
and their row counts. **The marker is the commit**: readers (`committed_files`, and through it
`load`, `open_table`, curation, stats and the retrieval index) read only the files that markers
name. So a failure anywhere before the marker, between two moves or between the last move and
the marker, shows no row to any of them; only a plain directory read would see the moved files,
and those are replaced by the redone shard with the same rows, or deleted by the next run's
cleanup (`remove_uncommitted`).

Final names depend only on the shard, so a redone shard replaces what an interrupted attempt
left, and the marker, written whole (`Store.write_bytes`), is either there or not. A marker that
cannot be read is treated as absent: its shard is redone.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import pyarrow as pa
import pyarrow.parquet as pq

from links_ray.data.schemas import CURATION_TABLES, GENERATION_TABLES, PARQUET_OPTIONS, SCHEMAS
from links_ray.data.store import META, TEMPORARY_PREFIX, Store

#: Each stage's marker folder (under `ROOT/_links/`) and the tables its shards write.
STAGE_TABLES = {"shards": GENERATION_TABLES, "curation": CURATION_TABLES}
#: The stage whose markers commit each table's files.
TABLE_STAGE = {table: stage for stage, tables in STAGE_TABLES.items() for table in tables}
#: Markers read at once: a store answers many small reads in parallel far faster than in turn.
MARKER_READERS = 16
#: Age after which a protocol temporary (`_tmp-*`) is litter from a failed write, not one under way.
STALE_TEMPORARY_S = 3600.0

#: Called with the name of each step a commit has just finished ("closed", "moved <table>",
#: "marked"): the fault tests' way to stop a commit between any two of its steps.
Failpoint = Callable[[str], None]


def shard_file(table: str, n_joints: int, shard_id: int) -> str:
    """The final path of a shard's file, relative to the root."""
    return f"{table}/n_joints={n_joints}/shard-{shard_id:06d}.parquet"


def marker_file(shard_id: int, stage: str = "shards") -> str:
    return f"{META}/{stage}/shard-{shard_id:06d}.json"


def _shard_id(name: str, prefix: str, suffix: str) -> int | None:
    """The shard id in a file name like `<prefix>000042<suffix>`, or None."""
    if not (name.startswith(prefix) and name.endswith(suffix)):
        return None
    digits = name[len(prefix) : len(name) - len(suffix)]
    return int(digits) if digits.isdigit() else None


def committed_shards(store: Store, stage: str = "shards") -> dict[int, dict]:
    """The markers of the shards `stage` committed, by shard id; unreadable ones are left out."""
    if stage not in STAGE_TABLES:
        raise ValueError(f"stage must be one of {', '.join(STAGE_TABLES)}, got {stage!r}")
    names = {}
    for relative in store.list_files(f"{META}/{stage}"):
        shard = _shard_id(relative.rsplit("/", 1)[-1], "shard-", ".json")
        if shard is not None:
            names[shard] = relative
    with ThreadPoolExecutor(MARKER_READERS) as pool:
        markers = dict(zip(names, pool.map(store.read_json, names.values()), strict=True))
    return {
        shard: marker
        for shard, marker in sorted(markers.items())
        if _well_formed(marker, shard, STAGE_TABLES[stage])
    }


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
    """Delete what attempts of `stage` left without a commit; returns how many files.

    That is: hidden attempt files, final files of shards without a marker (moved before a
    failure), and the protocol's unfinished small files. Only the holder of the root's writer
    lease may call this: it would delete a concurrent writer's work in progress.
    """
    removed = 0
    for table in STAGE_TABLES[stage]:
        for relative in store.list_files(table):
            name = relative.rsplit("/", 1)[-1]
            shard = _shard_id(name, "shard-", ".parquet")
            uncommitted = shard is not None and relative not in _named(markers, shard, table)
            if name.startswith("_shard-") or uncommitted:
                removed += store.delete(relative)
    # A reader may be writing the index cache right now: only old temporaries are litter.
    stale = time.time() - STALE_TEMPORARY_S
    for relative, modified in store.list_files(META, with_times=True):
        if relative.rsplit("/", 1)[-1].startswith(TEMPORARY_PREFIX) and modified < stale:
            removed += store.delete(relative)
    return removed


def _named(markers: dict[int, dict], shard: int, table: str) -> tuple[str, ...]:
    marker = markers.get(shard)
    return (marker["files"][table],) if marker and table in marker["files"] else ()


class ShardWriter:
    """Streams one shard's record batches into hidden files, then commits them together."""

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
        self.attempt = uuid.uuid4().hex[:12]
        self.rows: dict[str, int] = {}
        self._failpoint = failpoint
        self._writers: dict[str, pq.ParquetWriter] = {}
        self._streams: dict[str, pa.NativeFile] = {}
        self._moved: list[str] = []

    def _temporary(self, table: str) -> str:
        folder, name = shard_file(table, self.n_joints, self.shard_id).rsplit("/", 1)
        return f"{folder}/_{name.removesuffix('.parquet')}.{self.attempt}.parquet"

    def _step(self, name: str) -> None:
        if self._failpoint is not None:
            self._failpoint(name)

    def write(self, table: str, batch: pa.RecordBatch) -> None:
        """Append rows (with the table's schema) to the shard's file for `table`."""
        if table not in STAGE_TABLES[self.stage]:
            raise ValueError(f"the {self.stage} stage writes no {table} table")
        if table not in self._writers:
            relative = self._temporary(table)
            self.store._make_parent(relative)
            stream = self.store.fs.open_output_stream(self.store.path(relative))
            self._streams[table] = stream
            self._writers[table] = pq.ParquetWriter(stream, SCHEMAS[table], **PARQUET_OPTIONS)
        self._writers[table].write_batch(batch)
        self.rows[table] = self.rows.get(table, 0) + batch.num_rows

    def commit(self, stats: dict) -> dict:
        """Close the files, move them to their final names, then write the marker (the commit);
        returns the marker."""
        for table, writer in self._writers.items():
            writer.close()
            self._streams[table].close()
        self._step("closed")
        files = {}
        for table in self._writers:
            final = shard_file(table, self.n_joints, self.shard_id)
            self.store.fs.move(self.store.path(self._temporary(table)), self.store.path(final))
            self._moved.append(final)
            files[table] = final
            self._step(f"moved {table}")
        marker = {
            "shard": self.shard_id,
            "n_joints": self.n_joints,
            "attempt": self.attempt,
            "files": files,
            "rows": self.rows,
            "stats": stats,
        }
        self.store.write_json(marker_file(self.shard_id, self.stage), marker)
        self._step("marked")
        return marker

    def abort(self) -> None:
        """Leave nothing of this attempt behind, unless the shard's marker is there (then it is
        committed). Never raises: it runs while another error is on its way up, and what it
        cannot delete the next run's cleanup will."""
        for table, writer in self._writers.items():
            for close in (writer.close, self._streams[table].close):
                try:
                    close()
                except Exception:  # the error being handled is the one to report
                    pass
        try:
            marker = self.store.read_json(marker_file(self.shard_id, self.stage))
        except Exception:  # unknown: keep the moved files for the next run
            return
        if marker is not None:  # committed, by this attempt or another: its files stay
            return
        for table in self._writers:
            self.store.delete(self._temporary(table))
        for final in self._moved:
            self.store.delete(final)
