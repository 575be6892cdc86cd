"""Reading the LINKS release's pickled files without running what they name.

A release file is a sequence of pickles, one `pickle.dump` per batch. Unpickling runs whatever
callable a pickle names, so `read_batches` unpickles with `ReleaseUnpickler`, which resolves
only the names a plain `pickle.dump` of lists of numpy arrays and scalars uses (protocols 0 to
5, numpy 1 and numpy 2 module names) and refuses any other before anything is called. Lists,
tuples, ints, floats, bools and strings need no name at all.

Pure numpy: no Ray.
"""

from __future__ import annotations

import codecs
import io
import pickle
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.fs as pafs

from links_ray.data.store import Store

try:  # numpy 2 keeps its internals in numpy._core; numpy 1 in numpy.core
    from numpy._core import multiarray as _multiarray
    from numpy._core import numeric as _numeric
except ImportError:  # pragma: no cover - numpy 1
    from numpy.core import multiarray as _multiarray  # type: ignore[no-redef]
    from numpy.core import numeric as _numeric  # type: ignore[no-redef]

#: The release's four files by released name, and the prefix the release's generator puts
#: before its dataset's name (NAME, Solutions_NAME, Normalized_NAME, Curated_Normalized_NAME).
RELEASE_FILES = {
    "dataset": "",
    "simulation_dataset": "Solutions_",
    "normalized_dataset": "Normalized_",
    "curated_dataset": "Curated_Normalized_",
}
#: Bytes read from the store at once.
READ_BUFFER = 8 * 1024 * 1024


class ReleaseFileError(ValueError):
    """A release file that cannot be read as the release writes it: a refused name, a
    truncated or damaged batch, or contents of the wrong shape or type."""


def _latin1(text: object, encoding: str = "latin1") -> bytes:
    """`_codecs.encode` as protocols 0-2 use it for bytes: a string to latin-1, nothing else
    (other codecs would let a pickle run arbitrary codec machinery)."""
    if not isinstance(text, str) or codecs.lookup(encoding).name != "iso8859-1":
        raise pickle.UnpicklingError("_codecs.encode is read only for latin-1 text")
    return text.encode("latin1")


def _dtype(spec: object, align: bool = False, copy: bool = False) -> np.dtype:
    """`numpy.dtype` for plain numeric, bool and byte-string types only: an object dtype would
    let the array's items name anything."""
    dtype = np.dtype(spec, align, copy)  # type: ignore[call-overload]
    if dtype.hasobject:
        raise pickle.UnpicklingError("object arrays are not read")
    return dtype


def _reconstruct(subtype: object, shape: object, dtype: object) -> np.ndarray:
    """numpy's array reconstructor as its pickles call it: a plain, empty array whose shape and
    data the pickle then sets from bytes it holds, so an array is never larger than its file."""
    if subtype is not np.ndarray or shape != (0,):
        raise pickle.UnpicklingError("arrays are read only as numpy pickles them")
    return _multiarray._reconstruct(np.ndarray, (0,), dtype)


_NUMPY_NAMES: dict[str, Callable[..., Any] | type] = {
    "_reconstruct": _reconstruct,
    "scalar": _multiarray.scalar,
}
#: Every name a release file may hold, module by module.
ALLOWED_GLOBALS: dict[tuple[str, str], Callable[..., Any] | type] = {
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): _dtype,
    ("_codecs", "encode"): _latin1,
    **{
        (f"{module}.multiarray", name): f
        for module in ("numpy.core", "numpy._core")
        for name, f in _NUMPY_NAMES.items()
    },
    **{
        (f"{module}.numeric", "_frombuffer"): _numeric._frombuffer
        for module in ("numpy.core", "numpy._core")
    },
}


class RefusedName(pickle.UnpicklingError):
    """A pickle names a global the release's files never hold."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.name = name


class ReleaseUnpickler(pickle.Unpickler):
    """An unpickler that resolves only `ALLOWED_GLOBALS` and refuses out-of-band buffers and
    persistent ids."""

    def find_class(self, module: str, name: str) -> Any:
        """The allowed object `module.name` stands for; RefusedName for any other."""
        found = ALLOWED_GLOBALS.get((module, name))
        if found is None:
            raise RefusedName(f"{module}.{name}")
        return found

    def persistent_load(self, pid: Any) -> Any:
        """Always RefusedName: the release's files hold no persistent ids."""
        raise RefusedName("a persistent id")


def release_files(store: Store) -> dict[str, str | None]:
    """The release's files at the root of `store`, by released name (RELEASE_FILES), each
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
        prefix = RELEASE_FILES["simulation_dataset"]
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
    for name, prefix in RELEASE_FILES.items():
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
    """A store's input stream as a raw file, for io.BufferedReader."""

    def __init__(self, stream: pa.NativeFile) -> None:
        self._stream = stream
        self._position = 0

    def readable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._position

    def readinto(self, buffer: Any) -> int:
        data = self._stream.read(len(buffer))
        buffer[: len(data)] = data
        self._position += len(data)
        return len(data)


def read_batches(store: Store, relative: str) -> Iterator[tuple[int, int, Any]]:
    """(batch number, byte offset, object) of each pickle of a release file, one at a time.

    Raises ReleaseFileError naming the file, the batch and its offset for a refused name
    (nothing it names is called), a batch cut short, or one that is not a pickle. The
    iterator keeps no reference to a batch it has handed out: a caller that drops one frees it
    before the next is read.
    """
    shown = f"{store.uri}/{relative}"
    with store.fs.open_input_stream(store.path(relative)) as stream:
        source = io.BufferedReader(_Source(stream), READ_BUFFER)
        batch = 0
        while True:
            offset = source.tell()
            if not source.peek(1):
                return
            yield batch, offset, _load(source, f"{shown} batch {batch}", offset)
            batch += 1


def _load(source: io.BufferedReader, shown: str, offset: int) -> Any:
    """One batch's object, read at `offset`; ReleaseFileError saying why it cannot be."""
    try:
        return ReleaseUnpickler(source).load()
    except RefusedName as exc:
        raise ReleaseFileError(
            f"{shown} names {exc.name}; only numpy arrays and lists are read"
        ) from None
    except (EOFError, pickle.UnpicklingError, ValueError, TypeError, IndexError, KeyError) as exc:
        if not source.peek(1):
            raise ReleaseFileError(
                f"{shown} at byte {offset} is cut short: the file ends inside it, at byte "
                f"{source.tell()}"
            ) from None
        raise ReleaseFileError(
            f"{shown} at byte {offset} is not a readable pickle: {exc}"
        ) from None
