"""Where the dataset lives: table schemas, the filesystem, and the shard commit protocol.

A dataset root is a local folder or ``s3://bucket/prefix``. Each table is Hive-partitioned
Parquet (docs/CONTRACT.md, Dataset layout)::

    ROOT/mechanisms/n_joints=12/shard-000042.parquet
    ROOT/simulations/n_joints=12/shard-000042.parquet
    ROOT/negatives/n_joints=12/shard-000042.parquet
    ROOT/_links/run.json                 what was asked: seed, count, sampler, shard size
    ROOT/_links/shards/shard-000042.json commit marker: files, rows and statistics of a shard
    ROOT/_links/summary.json             the run summary

Commit protocol: a shard streams into files named ``_shard-000042.<attempt>.parquet``, which
readers skip (pyarrow ignores names starting with ``_``); once every file of the shard is
complete they are moved to their final names, and then the marker is written. Final names
depend only on the shard, so a redone shard replaces what an interrupted attempt left rather
than adding to it; a shard without a marker is redone on the next run.

S3 settings and credentials come from the standard AWS variables and chain
(``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``, ``AWS_REGION``, ``~/.aws``, instance roles, ...).
Nothing here logs or stores them.

Pure pyarrow: no Ray.
"""

from __future__ import annotations

import json
import os
import uuid
from dataclasses import dataclass, field
from urllib.parse import urlparse

import pyarrow as pa
import pyarrow.fs as pafs
import pyarrow.parquet as pq

GENERATION_TABLES = ("mechanisms", "simulations", "negatives")
CURATION_TABLES = ("paths", "curated")
META = "_links"

_MECHANISM_FIELDS = [
    pa.field("mechanism_id", pa.int64(), nullable=False),
    pa.field("topology_id", pa.int64(), nullable=False),
    pa.field("variant", pa.int8(), nullable=False),
    pa.field("adjacency", pa.list_(pa.uint8()), nullable=False),
    pa.field("node_types", pa.list_(pa.int8()), nullable=False),
    pa.field("positions", pa.list_(pa.float64()), nullable=False),
]
_PATH_SCHEMA = pa.schema(
    [
        pa.field("path_id", pa.int64(), nullable=False),
        pa.field("mechanism_id", pa.int64(), nullable=False),
        pa.field("joint", pa.int8(), nullable=False),
        pa.field("points", pa.list_(pa.float32()), nullable=False),
        pa.field("is_arc", pa.bool_(), nullable=False),
        pa.field("is_circle", pa.bool_(), nullable=False),
        pa.field("circle_variance", pa.float32(), nullable=False),
    ]
)
#: Columns of each table as written; `n_joints` is the Hive partition (the folder name).
SCHEMAS: dict[str, pa.Schema] = {
    "mechanisms": pa.schema(_MECHANISM_FIELDS),
    "simulations": pa.schema(
        [
            pa.field("mechanism_id", pa.int64(), nullable=False),
            pa.field("steps", pa.int16(), nullable=False),
            pa.field("trajectories", pa.list_(pa.float32()), nullable=False),
        ]
    ),
    "negatives": pa.schema(
        [
            *_MECHANISM_FIELDS,
            pa.field("locked_step", pa.int16(), nullable=False),
            pa.field("locked_node", pa.int16(), nullable=False),
        ]
    ),
    "paths": _PATH_SCHEMA,
    "curated": _PATH_SCHEMA,
}
#: zstd, no dictionary: floats do not repeat, and dictionary pages only cost time and space.
PARQUET_OPTIONS = {"compression": "zstd", "use_dictionary": False, "write_statistics": True}


class StoreError(ValueError):
    """The dataset root cannot be used: unreachable, refused, or not a place to write."""


def _s3_filesystem(bucket: str, attempts: int) -> pafs.S3FileSystem:
    """An S3 filesystem configured only from the standard AWS variables and chain."""
    endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
    options: dict = {
        "region": os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION"),
        "connect_timeout": 3,
        "request_timeout": 60,
        "retry_strategy": pafs.AwsStandardS3RetryStrategy(max_attempts=attempts),
    }
    if endpoint:
        parsed = urlparse(endpoint if "://" in endpoint else f"https://{endpoint}")
        options["endpoint_override"] = parsed.netloc
        options["scheme"] = parsed.scheme
    if not options["region"] and not endpoint:
        options["region"] = pafs.resolve_s3_region(bucket)
    return pafs.S3FileSystem(**options)


@dataclass
class Store:
    """A dataset root on a pyarrow filesystem."""

    uri: str
    fs: pafs.FileSystem
    root: str  # the root's path inside `fs`
    _made: set[str] = field(default_factory=set, repr=False)

    @classmethod
    def open(cls, uri: str, attempts: int = 2, writable: bool = True) -> Store:
        """Resolve `uri` and prove it usable, else `StoreError`: for writers, that a file can be
        written, read and deleted there; for readers (`writable=False`), that it exists.

        `attempts` bounds each S3 request's tries: few to fail fast when checking a root,
        more for long runs that should ride out a store's brief refusals.
        """
        if not isinstance(uri, str) or not uri.strip():
            raise StoreError(f"--out must be a folder or s3://bucket/prefix, got {uri!r}")
        uri = uri.strip().rstrip("/")
        parsed = urlparse(uri)
        if parsed.scheme == "s3":
            if not parsed.netloc:
                raise StoreError(f"{uri} names no bucket")
            fs: pafs.FileSystem = _s3_filesystem(parsed.netloc, attempts)
            root = f"{parsed.netloc}{parsed.path}"
        elif parsed.scheme in ("", "file"):
            fs = pafs.LocalFileSystem()
            root = os.path.abspath(parsed.path if parsed.scheme else uri)
        else:
            raise StoreError(
                f"unsupported scheme {parsed.scheme!r} in {uri}: use a folder or s3://"
            )
        store = cls(uri=uri, fs=fs, root=root)
        try:
            store._probe_writes() if writable else store._probe_reads()
        except StoreError:
            raise
        except (OSError, pa.ArrowException) as exc:
            raise StoreError(f"cannot use {uri}: {_diagnose(exc)}") from None
        return store

    def _probe_writes(self) -> None:
        probe = f"{META}/_probe-{uuid.uuid4().hex}"
        self.write_bytes(probe, b"ok")
        if self.read_bytes(probe) != b"ok":
            raise StoreError(f"{self.uri}: a probe file read back different bytes")
        self.fs.delete_file(self.path(probe))

    def _probe_reads(self) -> None:
        # Listing the root asks the store (and its credentials) for something real; what is
        # missing there is for the reader to say.
        self.fs.get_file_info(pafs.FileSelector(self.root, allow_not_found=True))

    def path(self, relative: str) -> str:
        return f"{self.root}/{relative}"

    def _make_parent(self, relative: str) -> None:
        parent = self.path(relative).rsplit("/", 1)[0]
        if parent not in self._made:
            self.fs.create_dir(parent, recursive=True)
            self._made.add(parent)

    def write_bytes(self, relative: str, data: bytes) -> None:
        self._make_parent(relative)
        with self.fs.open_output_stream(self.path(relative)) as stream:
            stream.write(data)

    def read_bytes(self, relative: str) -> bytes | None:
        """The file's bytes, or None if it does not exist."""
        try:
            with self.fs.open_input_stream(self.path(relative)) as stream:
                return stream.read()
        except FileNotFoundError:
            return None

    def write_json(self, relative: str, value: dict) -> None:
        self.write_bytes(relative, (json.dumps(value, indent=1) + "\n").encode())

    def read_json(self, relative: str) -> dict | None:
        data = self.read_bytes(relative)
        return None if data is None else json.loads(data)

    def list_files(self, relative: str) -> list[str]:
        """Paths (relative to the root) of the files below `relative`, recursively."""
        selector = pafs.FileSelector(self.path(relative), recursive=True, allow_not_found=True)
        prefix = len(self.root) + 1
        return sorted(
            info.path[prefix:]
            for info in self.fs.get_file_info(selector)
            if info.type == pafs.FileType.File
        )

    def claim(self, relative: str, config: dict) -> None:
        """Record what a run asks for at `relative`, or check it matches what is recorded.

        A root holds one dataset: resuming with other options would mix two datasets' rows.
        """
        recorded = self.read_json(relative)
        if recorded is None:
            self.write_json(relative, config)
        elif recorded != config:
            differ = ", ".join(
                f"{k}={recorded.get(k)}" for k in config if recorded.get(k) != config[k]
            )
            raise StoreError(
                f"{self.uri} holds another run ({differ}); use a new root or the same options"
            )

    # -- shards ---------------------------------------------------------------------------

    def committed_shards(self, stage: str = "shards") -> dict[int, dict]:
        """Markers of the shards a stage ("shards": generation, "curation") committed, by id."""
        markers = {}
        for relative in self.list_files(f"{META}/{stage}"):
            name = relative.rsplit("/", 1)[-1]
            if name.startswith("shard-") and name.endswith(".json"):
                markers[int(name[6:-5])] = self.read_json(relative)
        return markers

    def remove_uncommitted(self, tables: tuple[str, ...]) -> int:
        """Delete files that interrupted attempts left in `tables` (names starting `_shard-`)."""
        removed = 0
        for table in tables:
            for relative in self.list_files(table):
                if relative.rsplit("/", 1)[-1].startswith("_shard-"):
                    self.fs.delete_file(self.path(relative))
                    removed += 1
        return removed


def shard_file(table: str, n_joints: int, shard_id: int) -> str:
    """The final (visible) path of a shard's file, relative to the root."""
    return f"{table}/n_joints={n_joints}/shard-{shard_id:06d}.parquet"


def marker_file(shard_id: int, stage: str = "shards") -> str:
    return f"{META}/{stage}/shard-{shard_id:06d}.json"


class ShardWriter:
    """Streams one shard's record batches into hidden files, then commits them together."""

    def __init__(self, store: Store, shard_id: int, n_joints: int, stage: str = "shards") -> None:
        self.store = store
        self.shard_id = shard_id
        self.n_joints = n_joints
        self.stage = stage
        self.attempt = uuid.uuid4().hex[:12]
        self.rows: dict[str, int] = {}
        self._writers: dict[str, pq.ParquetWriter] = {}
        self._streams: dict[str, pa.NativeFile] = {}

    def _temporary(self, table: str) -> str:
        final = shard_file(table, self.n_joints, self.shard_id)
        folder, name = final.rsplit("/", 1)
        return f"{folder}/_{name[:-8]}.{self.attempt}.parquet"

    def write(self, table: str, batch: pa.RecordBatch) -> None:
        """Append rows (with the table's schema) to the shard's file for `table`."""
        if table not in self._writers:
            relative = self._temporary(table)
            self.store._make_parent(relative)
            stream = self.store.fs.open_output_stream(self.store.path(relative))
            self._streams[table] = stream
            self._writers[table] = pq.ParquetWriter(stream, SCHEMAS[table], **PARQUET_OPTIONS)
        self._writers[table].write_batch(batch)
        self.rows[table] = self.rows.get(table, 0) + batch.num_rows

    def _close(self) -> None:
        for table, writer in self._writers.items():
            writer.close()
            self._streams[table].close()

    def commit(self, stats: dict) -> dict:
        """Make the shard's files visible, then write its marker; returns the marker."""
        self._close()
        files = {}
        for table in self._writers:
            final = shard_file(table, self.n_joints, self.shard_id)
            self.store.fs.move(self.store.path(self._temporary(table)), self.store.path(final))
            files[table] = final
        marker = {
            "shard": self.shard_id,
            "n_joints": self.n_joints,
            "files": files,
            "rows": self.rows,
            "stats": stats,
        }
        self.store.write_json(marker_file(self.shard_id, self.stage), marker)
        return marker

    def abort(self) -> None:
        """Close and delete this attempt's hidden files."""
        for table, writer in self._writers.items():
            try:
                writer.close()
                self._streams[table].close()
            finally:
                self.store.fs.delete_file(self.store.path(self._temporary(table)))


#: AWS error codes in pyarrow's messages, and what they mean to a user.
_S3_DIAGNOSES = {
    "SIGNATURE_DOES_NOT_MATCH": "credentials refused (AWS_SECRET_ACCESS_KEY or the chain's)",
    "INVALID_ACCESS_KEY_ID": "credentials refused (unknown AWS_ACCESS_KEY_ID)",
    "ACCESS_DENIED": "access denied: check the credentials and the bucket's permissions",
    "NETWORK_CONNECTION": "store unreachable: check AWS_ENDPOINT_URL and the network",
    "NO_SUCH_BUCKET": "no such bucket",
}


def _diagnose(exc: BaseException) -> str:
    """One line saying what went wrong, without secrets (pyarrow's messages carry none)."""
    text = str(exc).strip() or type(exc).__name__
    for code, meaning in _S3_DIAGNOSES.items():
        if code in text:
            return f"{meaning} [{code}]"
    return text.splitlines()[0]
