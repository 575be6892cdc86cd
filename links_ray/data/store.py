"""Where the dataset lives: a root on a pyarrow filesystem, a local folder or S3.

The store reads and writes files by their path relative to the root, and gives the commit
protocol (`links_ray.data.commit`) and the leases (`links_ray.data.lease`) the few guarantees
they build on:

- a small file is written whole or not at all: into a hidden temporary name, then moved to its
  own (a rename on a local disk; on S3 a copy, which makes the object appear whole);
- `read_json` treats a file it cannot parse like a missing one, so a damaged marker or cache
  means "redo" or "rebuild", never a crash;
- create-only writes (`create_exclusive`), by which exactly one of several writers of a file
  wins: on S3 the store's own precondition (If-None-Match), on a local disk a hard link of a
  whole, synced temporary file onto the name (the link fails if the name exists);
- conditional replaces and deletes for leases: on S3 If-Match, on a local disk a lock file held
  for the few microseconds of a compare and a write;
- on a local disk, `sync_file` and `sync_folder`, by which a commit survives a power loss (on S3
  an acknowledged write is durable, and both do nothing).

The run record (`_links/run.json`) says what made a root; `refuse_imported` keeps the commands
that generate or curate out of a root the release's import wrote.

A writable S3 root is checked at `open` to refuse a second create-only write: a store that
ignores or refuses If-None-Match is named in one line, never used without it.

S3 settings and credentials come from the standard AWS variables and chain
(``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``, ``AWS_REGION``, ``~/.aws``, instance roles, ...).
Nothing here logs or stores them.

pyarrow and boto3: no Ray.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from urllib.parse import urlparse

import pyarrow as pa
import pyarrow.fs as pafs
import pyarrow.parquet as pq

#: The folder of the protocol's own files (markers, run records, leases, the index cache).
META = "_links"
#: Prefix of the hidden temporary names small files are written under before their move.
TEMPORARY_PREFIX = "_tmp-"
#: The run record's (`_links/run.json`) `source` in a root that `links import-release` wrote.
IMPORTED_SOURCE = "links-release"


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
    attempts: int = 2
    _made: set[str] = field(default_factory=set, repr=False)
    _client: object = field(default=None, repr=False)

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
        store = cls(uri=uri, fs=fs, root=root, attempts=attempts)
        try:
            store._probe_writes() if writable else store._probe_reads()
        except StoreError:
            raise
        except (OSError, pa.ArrowException) as exc:
            raise StoreError(f"cannot use {uri}: {diagnose(exc)}") from None
        return store

    def _probe_writes(self) -> None:
        probe = f"{META}/_probe-{uuid.uuid4().hex}"
        self.write_bytes(probe, b"ok")
        try:
            if self.read_bytes(probe) != b"ok":
                raise StoreError(f"{self.uri}: a probe file read back different bytes")
            if self.is_s3 and self.create_exclusive(probe, b"again") is not None:
                raise StoreError(
                    f"{self.uri}: the S3 store ignores If-None-Match (it replaced an existing "
                    "object): commits and leases need create-only writes"
                )
        finally:
            self.delete(probe)

    def _probe_reads(self) -> None:
        # Listing the root asks the store (and its credentials) for something real; what is
        # missing there is for the reader to say.
        self.fs.get_file_info(pafs.FileSelector(self.root, allow_not_found=True))

    def path(self, relative: str) -> str:
        """The full path (bucket and prefix for S3) of `relative`, a path under the root."""
        return f"{self.root}/{relative}"

    @property
    def is_local(self) -> bool:
        """Whether the root is a folder on this machine."""
        return isinstance(self.fs, pafs.LocalFileSystem)

    def _make_parent(self, relative: str) -> None:
        parent = self.path(relative).rsplit("/", 1)[0]
        if parent not in self._made:
            self.fs.create_dir(parent, recursive=True)
            if self.is_local:  # the new folders' entries, so that a synced file in them lasts
                folder, top = parent, os.path.dirname(self.root)
                while len(folder) >= len(top):
                    _sync_path(folder)
                    folder = os.path.dirname(folder)
            self._made.add(parent)

    def sync_file(self, relative: str) -> None:
        """On a local disk, flush the file's bytes to the device (on S3: nothing to do)."""
        if self.is_local:
            _sync_path(self.path(relative))

    def sync_folder(self, relative: str) -> None:
        """On a local disk, flush the folder's entries (names moved or linked into it)."""
        if self.is_local:
            _sync_path(self.path(relative) if relative else self.root)

    def _temporary(self, relative: str) -> str:
        folder, name = relative.rsplit("/", 1) if "/" in relative else ("", relative)
        return f"{folder}/{TEMPORARY_PREFIX}{uuid.uuid4().hex[:12]}-{name}".lstrip("/")

    def write_bytes(self, relative: str, data: bytes) -> None:
        """Write a file whole or not at all: a hidden temporary name first, then the move."""
        self._make_parent(relative)
        temporary = self._temporary(relative)
        try:
            with self.fs.open_output_stream(self.path(temporary)) as stream:
                stream.write(data)
            self.fs.move(self.path(temporary), self.path(relative))
        except BaseException:
            self.delete(temporary)
            raise

    def delete(self, relative: str) -> bool:
        """Delete a file if it is there; False if it was not, or could not be deleted."""
        try:
            self.fs.delete_file(self.path(relative))
            return True
        except (OSError, pa.ArrowException):
            return False

    def delete_folder(self, relative: str) -> bool:
        """Delete a folder and everything below it; False if it could not be deleted."""
        try:
            self.fs.delete_dir(self.path(relative))
            return True
        except FileNotFoundError:
            return True
        except (OSError, pa.ArrowException):
            return False

    def read_bytes(self, relative: str) -> bytes | None:
        """The file's bytes, or None if it does not exist."""
        try:
            with self.fs.open_input_stream(self.path(relative)) as stream:
                return stream.read()
        except FileNotFoundError:
            return None

    def read_parquet(self, relative: str, columns: list[str] | None = None) -> pa.Table:
        """One Parquet file's rows (no partition columns: those are in its folders' names)."""
        with self.fs.open_input_file(self.path(relative)) as source:
            return pq.read_table(source, columns=columns)

    def write_json(self, relative: str, value: dict) -> None:
        """Write `value` as indented JSON, whole or not at all (`write_bytes`)."""
        self.write_bytes(relative, (json.dumps(value, indent=1) + "\n").encode())

    def read_json(self, relative: str) -> dict | None:
        """The file's JSON object, or None if it is missing or not a readable JSON object."""
        data = self.read_bytes(relative)
        if data is None:
            return None
        try:
            value = json.loads(data)
        except (UnicodeDecodeError, json.JSONDecodeError):
            return None
        return value if isinstance(value, dict) else None

    def list_files(self, relative: str, with_times: bool = False) -> list:
        """Paths (relative to the root) of the files below `relative`, recursively, sorted;
        with `with_times`, (path, modified seconds since the epoch) pairs."""
        selector = pafs.FileSelector(self.path(relative), recursive=True, allow_not_found=True)
        prefix = len(self.root) + 1
        files = sorted(
            (info.path[prefix:], info.mtime.timestamp() if info.mtime else 0.0)
            for info in self.fs.get_file_info(selector)
            if info.type == pafs.FileType.File
        )
        return files if with_times else [path for path, _ in files]

    def claim(self, relative: str, config: dict, defaults: dict | None = None) -> None:
        """Record what a run asks for at `relative`, or check it matches what is recorded.

        A root holds one dataset: resuming with other options would mix two datasets' rows.
        The record is created only if absent, so two runs racing to claim a root cannot both
        win; an unreadable record counts as absent. `defaults` are the values of options a
        record made before they existed holds implicitly.
        """
        encoded = (json.dumps(config, indent=1) + "\n").encode()
        recorded = self.read_json(relative)
        if recorded is None:
            if self.create_exclusive(relative, encoded) is not None:
                return
            recorded = self.read_json(relative)
            if recorded is None:  # there, but unreadable: written by nobody whole, so ours
                self.write_bytes(relative, encoded)
                return
        recorded = {**(defaults or {}), **recorded}
        if recorded != config:
            differ = ", ".join(
                f"{k}={_option(recorded.get(k))}" for k in config if recorded.get(k) != config[k]
            )
            raise StoreError(
                f"{self.uri} holds another run ({differ}); use a new root or the same options"
            )

    # -- conditional writes, for commit markers and leases ----------------------------------
    # Each returns the file's new version tag (an S3 ETag, or a digest of a local file's
    # bytes), or None when its precondition did not hold.

    @property
    def is_s3(self) -> bool:
        """Whether the root is an S3 bucket (or prefix)."""
        return isinstance(self.fs, pafs.S3FileSystem)

    def read_versioned(self, relative: str) -> tuple[bytes, str] | None:
        """The file's bytes and version tag, or None if it does not exist."""
        if self.is_s3:
            try:
                answer = self._s3().get_object(**self._s3_key(relative))
            except Exception as exc:
                if _s3_code(exc) in ("NoSuchKey", "404"):
                    return None
                raise _s3_error(exc) from None
            return answer["Body"].read(), answer["ETag"]
        data = self.read_bytes(relative)
        return None if data is None else (data, _digest(data))

    def create_exclusive(self, relative: str, data: bytes) -> str | None:
        """Create the file with `data` only if it does not exist; of writers racing to create
        it exactly one succeeds. The file appears whole, and on a local disk it is synced."""
        if self.is_s3:
            return self._s3_put(relative, data, IfNoneMatch="*")
        # A link of a whole temporary file: readers never see a part of it, and the link,
        # unlike a rename, fails when the name exists. The guarded replaces and deletes never
        # leave the name absent while they change it, so they need not take turns with this.
        self._make_parent(relative)
        temporary = self.path(self._temporary(relative))
        try:
            with open(temporary, "wb") as stream:
                stream.write(data)
                stream.flush()
                os.fsync(stream.fileno())
            try:
                os.link(temporary, self.path(relative))
            except FileExistsError:
                return None
            except OSError as exc:
                if exc.errno in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV):
                    raise StoreError(
                        f"{self.uri}: the filesystem refuses hard links ({exc.strerror}), "
                        "which create-only writes use"
                    ) from None
                raise
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(temporary)
        self.sync_folder(relative.rsplit("/", 1)[0] if "/" in relative else "")
        return _digest(data)

    def replace_if(self, relative: str, version: str, data: bytes) -> str | None:
        """Replace the file with `data` only if it is still at `version`."""
        if self.is_s3:
            return self._s3_put(relative, data, IfMatch=version)
        with self._local_guard():
            current = self.read_bytes(relative)
            if current is None or _digest(current) != version:
                return None
            self.write_bytes(relative, data)
            return _digest(data)

    def delete_if(self, relative: str, version: str) -> bool:
        """Delete the file only if it is still at `version`."""
        if self.is_s3:
            try:
                self._s3().delete_object(**self._s3_key(relative), IfMatch=version)
                return True
            except Exception as exc:
                if _s3_code(exc) in (*_PRECONDITION_CODES, "NoSuchKey", "404"):
                    return False
                raise _s3_error(exc) from None
        with self._local_guard():
            current = self.read_bytes(relative)
            if current is None or _digest(current) != version:
                return False
            return self.delete(relative)

    @contextlib.contextmanager
    def _local_guard(self) -> Iterator[None]:
        """Hold this root's lock file: the conditional writes of all processes take turns.

        The kernel drops the lock when its holder dies, so a killed process never leaves it held.
        """
        import fcntl  # POSIX only, and only local roots need it

        self._make_parent(f"{META}/.guard")
        with open(self.path(f"{META}/.guard"), "a+b") as guard:
            fcntl.flock(guard, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(guard, fcntl.LOCK_UN)

    def _s3(self):  # a boto3 client: boto3 exports no type for it
        if self._client is None:
            self._client = _s3_client(self.attempts)
        return self._client

    def _s3_key(self, relative: str) -> dict[str, str]:
        bucket, _, prefix = self.path(relative).partition("/")
        return {"Bucket": bucket, "Key": prefix}

    def _s3_put(self, relative: str, data: bytes, **condition: str) -> str | None:
        try:
            return self._s3().put_object(**self._s3_key(relative), Body=data, **condition)["ETag"]
        except Exception as exc:
            code = _s3_code(exc)
            if code in _PRECONDITION_CODES:
                return None
            if code in _REFUSED_CONDITION_CODES:
                header = "If-None-Match" if "IfNoneMatch" in condition else "If-Match"
                raise StoreError(
                    f"{self.uri}: the S3 store refuses conditional writes ({header}: {code}); "
                    "commits and leases need them"
                ) from None
            raise _s3_error(exc) from None


#: What S3 answers when a conditional request's precondition fails (409: a concurrent one won).
_PRECONDITION_CODES = ("PreconditionFailed", "412", "ConditionalRequestConflict", "409")
#: What a store that does not implement a conditional write answers.
_REFUSED_CONDITION_CODES = ("NotImplemented", "501")


def refuse_imported(store: Store) -> dict:
    """The root's run record (`run.json`, {} if none); StoreError if `store` holds an import of
    the release: its curated set is the release's, which generating or curating more would mix
    with a seeded one."""
    run = store.read_json(f"{META}/run.json") or {}
    if run.get("source") == IMPORTED_SOURCE:
        raise StoreError(
            f"{store.uri} is an import of the LINKS release: only links import-release writes "
            "to it (run it again to finish an interrupted import)"
        )
    return run


def _sync_path(path: str) -> None:
    """fsync a local file or folder by its path."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _s3_client(attempts: int):  # a boto3 client
    """A boto3 S3 client from the same standard variables and chain as the filesystem."""
    import boto3
    from botocore.config import Config

    endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
    config = Config(
        connect_timeout=3,
        read_timeout=60,
        retries={"max_attempts": attempts, "mode": "standard"},
    )
    region = os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION")
    return boto3.session.Session().client(
        "s3", endpoint_url=endpoint or None, region_name=region, config=config
    )


def _s3_code(exc: BaseException) -> str:
    response = getattr(exc, "response", None) or {}
    return str(response.get("Error", {}).get("Code", ""))


def _s3_error(exc: BaseException) -> OSError:
    """An S3 client error as the OSError the filesystem would raise, named in one line."""
    code = _s3_code(exc)
    return OSError(f"{code or type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")


#: AWS error codes in pyarrow's messages, and what they mean to a user.
_S3_DIAGNOSES = {
    "SIGNATURE_DOES_NOT_MATCH": "credentials refused (AWS_SECRET_ACCESS_KEY or the chain's)",
    "INVALID_ACCESS_KEY_ID": "credentials refused (unknown AWS_ACCESS_KEY_ID)",
    "ACCESS_DENIED": "access denied: check the credentials and the bucket's permissions",
    "NETWORK_CONNECTION": "store unreachable: check AWS_ENDPOINT_URL and the network",
    "NO_SUCH_BUCKET": "no such bucket",
}


def diagnose(exc: BaseException) -> str:
    """One line saying what went wrong, without secrets (pyarrow's messages carry none)."""
    text = str(exc).strip() or type(exc).__name__
    for code, meaning in _S3_DIAGNOSES.items():
        if code in text:
            return f"{meaning} [{code}]"
    return text.splitlines()[0]


def _option(value: object) -> str:
    """A recorded option as a command line gives it: a list as comma-separated names."""
    return ",".join(map(str, value)) if isinstance(value, list) else str(value)
