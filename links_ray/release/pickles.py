"""Reading the LINKS release's pickled files without running what they name.

A release file is a sequence of pickles, one `pickle.dump` per batch. `read_batches` reads them
one at a time: before the unpickler reads a byte, the opcode filter of `release.opcode_scan`
has passed it (no dict or set, no opcode such pickles never hold, memo indices only in the
order a pickler writes them), and the unpickler is `release.unpickler.ReleaseUnpickler`, which
resolves only the names a plain `pickle.dump` of lists of numpy arrays and scalars uses and
makes the arrays itself from checked state. Both charge what the file's pickles make to one
ledger, a file's memory budget (`opcode_scan.memory_budget`, a small multiple of its size).
Whatever a file holds that cannot be read so is one `ReleaseFileError` naming the file, the
batch and its offset.

Pure numpy: no Ray.
"""

from __future__ import annotations

import io
import pickle
from collections.abc import Iterator
from typing import Any

import numpy as np
import pyarrow.fs as pafs

from links_ray.data.store import Store
from links_ray.release import opcode_scan
from links_ray.release.format import RELEASE_FILES
from links_ray.release.unpickler import RefusedName, ReleaseUnpickler

#: The prefix the release's generator puts before its dataset's name in each of the release's
#: four files (NAME, Solutions_NAME, Normalized_NAME, Curated_Normalized_NAME), by released name.
GENERATOR_PREFIXES = dict(
    zip(RELEASE_FILES, ("", "Solutions_", "Normalized_", "Curated_Normalized_"), strict=True)
)
#: Bytes read from the store at once.
READ_BUFFER = 8 * 1024 * 1024


class ReleaseFileError(ValueError):
    """A release file that cannot be read as the release writes it: a refused name, a
    truncated or damaged batch, or contents of the wrong shape or type."""


def release_files(store: Store) -> dict[str, str | None]:
    """The release's files at the root of `store`, by released name (`RELEASE_FILES`), each
    the path relative to the root or None if absent.

    Either released names (`dataset`, `simulation_dataset`, ...) or the generator's (`NAME`,
    `Solutions_NAME`, ...) are read: NAME is `dataset` when that file is there, else the one
    NAME with both `NAME` and `Solutions_NAME`. Raises ReleaseFileError if there is no dataset,
    several NAMEs, or one file under both its names.
    """
    selector = pafs.FileSelector(store.root, allow_not_found=True)
    files = {
        info.base_name
        for info in store.fs.get_file_info(selector)
        if info.type == pafs.FileType.File
    }
    if "dataset" in files:
        base = "dataset"
    else:
        prefix = GENERATOR_PREFIXES["simulation_dataset"]
        bases = sorted(
            name[len(prefix) :]
            for name in files
            if name.startswith(prefix) and name[len(prefix) :] in files
        )
        if not bases:
            raise ReleaseFileError(
                f"{store.uri} holds no release dataset: a file named dataset, or NAME beside "
                "Solutions_NAME"
            )
        if len(bases) > 1:
            raise ReleaseFileError(
                f"{store.uri} holds several release datasets ({', '.join(bases)}): keep one"
            )
        base = bases[0]
    found: dict[str, str | None] = {}
    for name, prefix in GENERATOR_PREFIXES.items():
        there = [
            candidate
            for candidate in dict.fromkeys((name if base == "dataset" else None, prefix + base))
            if candidate in files
        ]
        if len(there) > 1:
            raise ReleaseFileError(f"{store.uri} holds both {there[0]} and {there[1]}: keep one")
        found[name] = there[0] if there else None
    return found


class _Source(io.RawIOBase):
    """A stream as a raw file for io.BufferedReader, its bytes passed through the opcode filter
    (`release.opcode_scan`) for a file of `size` bytes: it ends just before the first opcode the
    filter refuses, and `refused` then says which and why (`cut_short` if the opcode's length
    runs past the file's end). `scan` is the filter's state, the file's memory ledger."""

    def __init__(self, stream: Any, size: int) -> None:
        self._stream = stream
        self._position = 0
        self.scan = opcode_scan.new_state(size)
        self.refused: str | None = None
        self.cut_short = False

    def readable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._position

    def readinto(self, buffer: Any) -> int:
        if self.refused is not None:
            return 0
        data = self._stream.read(len(buffer))
        # The unpickler reads ahead of the opcode it runs: bytes past a refused opcode must
        # never reach it, so they are held back here, where it reads them from.
        handed = opcode_scan.scan(np.frombuffer(data, np.uint8), self.scan)
        buffer[:handed] = data[:handed]
        self._position += handed
        if self.scan[opcode_scan.REASON] != 0:
            self.refused = opcode_scan.refusal(self.scan)
            self.cut_short = self.scan[opcode_scan.REASON] == opcode_scan.PAST_END
        return handed


def read_batches(store: Store, relative: str) -> Iterator[tuple[int, int, Any]]:
    """(batch number, byte offset, object) of each pickle of a release file, one at a time.

    Raises ReleaseFileError naming the file, the batch and its offset for a refused name
    (nothing it names is called), an opcode the release's files never hold (refused before the
    unpickler reads it), a batch cut short, or one that is not a pickle of the release's kind.
    The iterator keeps no reference to a batch it has handed out: a caller that drops one frees
    it before the next is read.
    """
    path = store.path(relative)
    with store.fs.open_input_stream(path) as stream:
        size = store.fs.get_file_info(path).size
        yield from read_pickles(stream, f"{store.uri}/{relative}", size)


def read_pickles(stream: Any, shown: str, size: int) -> Iterator[tuple[int, int, Any]]:
    """`read_batches` of a binary `stream` (anything with `read(n)`) of `size` bytes, open at
    its start, named `shown` in errors.

    What the file's pickles make together takes at most `opcode_scan.memory_budget(size)`
    bytes: a pickle may hand the same bytes to many arrays or strings, each a copy, and each is
    charged.
    """
    raw = _Source(stream, size)
    # A small file needs no larger buffer than itself.
    source = io.BufferedReader(raw, max(min(READ_BUFFER, size), 1))
    batch = 0
    while True:
        offset = source.tell()
        if not source.peek(1):
            if raw.refused is not None:  # refused where a batch would begin
                raise ReleaseFileError(
                    f"{shown} batch {batch} at byte {offset} is not a readable pickle: "
                    f"{raw.refused}"
                )
            return
        yield batch, offset, _load(source, raw, f"{shown} batch {batch}", offset, size)
        batch += 1


def _load(source: io.BufferedReader, raw: _Source, shown: str, offset: int, size: int) -> Any:
    """One batch's object, read at `offset` of a file of `size` bytes; ReleaseFileError saying
    why it cannot be."""
    try:
        return ReleaseUnpickler(source, raw.scan).load()
    except RefusedName as exc:
        raise ReleaseFileError(
            f"{shown} names {exc.name}; only numpy arrays and lists are read"
        ) from None
    except OSError:
        raise  # the store failed, not the file
    except Exception as exc:
        # A damaged or crafted batch can fail anywhere in the unpickler, in any exception;
        # each is the file's fault and ends the import in one line. The stream ends early at
        # an opcode the filter refused: running out there is that refusal, not the file's end.
        if _ran_out(exc) and not source.peek(1):
            if raw.refused is not None and not raw.cut_short:
                raise ReleaseFileError(
                    f"{shown} at byte {offset} is not a readable pickle: {raw.refused}"
                ) from None
            raise ReleaseFileError(
                f"{shown} at byte {offset} is cut short: the file ends inside it, at byte "
                f"{size if raw.cut_short else source.tell()}"
            ) from None
        raise ReleaseFileError(
            f"{shown} at byte {offset} is not a readable pickle: {_reason(exc)}"
        ) from None


def _ran_out(exc: Exception) -> bool:
    """Whether the unpickler failed for want of the pickle's next bytes."""
    return isinstance(exc, EOFError) or (
        type(exc) is pickle.UnpicklingError and str(exc) == "pickle data was truncated"
    )


def _reason(exc: Exception) -> str:
    """Why a batch failed, in one line of at most about 200 characters."""
    if isinstance(exc, MemoryError):
        return "it asks for more memory than there is"
    if isinstance(exc, RecursionError):
        return "it is nested too deeply"
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else f"{text[:200]}..."
