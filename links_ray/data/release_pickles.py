"""Reading the LINKS release's pickled files without running what they name.

A release file is a sequence of pickles, one `pickle.dump` per batch. Unpickling runs whatever
callable a pickle names, so `read_batches` unpickles with `ReleaseUnpickler`, which resolves
only the names a plain `pickle.dump` of lists of numpy arrays and scalars uses (protocols 0 to
5, numpy 1 and numpy 2 module names) and refuses any other before anything is called. Lists,
tuples, ints, floats, bools and strings need no name at all.

Nor does a pickle reach numpy's own constructors: what it names stands in for code of ours.
A pickle's BUILD step hands state from the file to the object's `__setstate__`, and numpy's
(of an array or a dtype) trusts that state, so the objects the unpickler makes are stand-ins
whose `__setstate__` accepts only the state numpy writes for a plain array: a dtype of the
kinds in `PLAIN_DTYPES`, then a shape and exactly the bytes that shape holds. The array is made
from those bytes by `np.frombuffer` and copied; once the pickle is loaded, each stand-in is
replaced by what it made.

Pure numpy: no Ray.
"""

from __future__ import annotations

import codecs
import io
import math
import pickle
import re
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.fs as pafs

from links_ray.data.store import Store

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
#: The dtypes an array or scalar of a release file may have, as numpy's pickles spell them
#: (kind and item size): bool, signed and unsigned ints, floats, and byte strings of any length.
PLAIN_DTYPES = re.compile(r"b1|[iuf][248]|[iu]1|S[1-9][0-9]{0,9}")
#: The most dimensions an array may have (numpy 2's own limit).
MAX_DIMENSIONS = 64


class ReleaseFileError(ValueError):
    """A release file that cannot be read as the release writes it: a refused name, a
    truncated or damaged batch, or contents of the wrong shape or type."""


class RefusedName(pickle.UnpicklingError):
    """A pickle names a global the release's files never hold."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.name = name


def _refuse(why: str) -> pickle.UnpicklingError:
    return pickle.UnpicklingError(why)


class _StandIn:
    """What the unpickler hands a pickle in place of a numpy object: `value` is the object once
    made (None until then). A BUILD of it is refused unless a subclass takes one."""

    __slots__ = ("value",)

    def __init__(self, value: Any = None) -> None:
        self.value = value

    def __setstate__(self, state: object) -> None:
        raise _refuse(f"a {self._what()} takes no BUILD")

    def _what(self) -> str:
        return type(self.value).__name__


class _Made(_StandIn):
    """An array (protocol 5's `_frombuffer`) or a scalar, made and checked when named."""

    __slots__ = ()


class _DtypeStandIn(_StandIn):
    """`numpy.dtype(spec)`, made when its one BUILD gives numpy's state of a plain dtype."""

    __slots__ = ("spec",)

    def __init__(self, spec: str) -> None:
        super().__init__()
        self.spec = spec

    def _what(self) -> str:
        return "dtype"

    def __setstate__(self, state: object) -> None:
        if self.value is not None:
            raise _refuse("a dtype is built twice")
        self.value = _plain_dtype(self.spec, state)


class _ArrayStandIn(_StandIn):
    """numpy's `_reconstruct` result: an array made when its one BUILD gives numpy's state of
    it, `(1, shape, dtype, is_fortran, data)`, within the unpickler's byte budget."""

    __slots__ = ("_unpickler",)

    def __init__(self, unpickler: ReleaseUnpickler) -> None:
        super().__init__()
        self._unpickler = unpickler

    def _what(self) -> str:
        return "array"

    def __setstate__(self, state: object) -> None:
        if self.value is not None:
            raise _refuse("an array is built twice")
        if type(state) is not tuple or len(state) != 5:
            raise _refuse("an array's state is not numpy's (version, shape, dtype, order, data)")
        version, shape, dtype, is_fortran, data = state
        if type(version) is not int or version != 1:
            raise _refuse("an array's state is not numpy's version 1")
        if type(is_fortran) not in (bool, int) or is_fortran not in (0, 1):
            raise _refuse("an array's order is not a bool")
        if type(data) is str:  # a Python 2 pickle's bytes, as numpy reads them
            data = data.encode("latin1")
        # numpy's own BUILD swaps a non-native array's bytes into native order.
        self.value = self._unpickler._array(
            data, dtype, shape, "F" if is_fortran else "C", native=True
        )


class _Marker:
    """`numpy.ndarray` as a pickle names it: nothing to call, only the subtype that
    `_reconstruct` is given."""

    __slots__ = ()

    def __setstate__(self, state: object) -> None:
        raise _refuse("numpy.ndarray takes no BUILD")

    def __repr__(self) -> str:
        return "numpy.ndarray"


_NDARRAY = _Marker()


class _Name:
    """An allowed global as a pickle sees it: it can be called, never changed by a BUILD."""

    __slots__ = ("_call", "_name")

    def __init__(self, call: Callable[..., Any], name: str) -> None:
        self._call = call
        self._name = name

    def __call__(self, *args: Any) -> Any:
        return self._call(*args)

    def __setstate__(self, state: object) -> None:
        raise _refuse(f"{self._name} takes no BUILD")

    def __repr__(self) -> str:
        return self._name


def _plain_dtype(spec: str, state: object) -> np.dtype:
    """The dtype `spec` with the byte order `state` gives, if `state` is numpy's own for it
    (versions 3 and 4: no subarray, names, fields or metadata, numpy's item size and
    alignment, no flags)."""
    if type(state) is not tuple or len(state) not in (8, 9):
        raise _refuse("a dtype's state is not numpy's")
    version, order, subarray, names, fields, size, alignment, flags, *metadata = state
    if type(version) is not int or version != len(state) - 5:
        raise _refuse("a dtype's state is not numpy's version 3 or 4")
    if not (subarray is names is fields is None) or (metadata and metadata[0] is not None):
        raise _refuse("a dtype has fields, a subarray or metadata; only plain dtypes are read")
    if type(flags) is not int or flags != 0:
        raise _refuse("a dtype has flags; only plain dtypes have none")
    dtype = np.dtype(spec)
    wanted = (dtype.itemsize, 1) if dtype.kind == "S" else (-1, -1)
    if type(size) is not int or type(alignment) is not int or (size, alignment) != wanted:
        raise _refuse(f"a {spec} dtype's item size or alignment is not numpy's")
    orders = ("|",) if dtype.kind == "S" or dtype.itemsize == 1 else ("<", ">")
    if type(order) is not str or order not in orders:
        raise _refuse(f"a {spec} dtype's byte order is not one numpy writes")
    return dtype if order == "|" else dtype.newbyteorder(order)


def _built_dtype(dtype: object) -> np.dtype:
    if type(dtype) is not _DtypeStandIn or dtype.value is None:
        raise _refuse("an array's dtype is not a dtype the pickle has built")
    return dtype.value


def _shape(shape: object) -> tuple[int, ...]:
    if (
        type(shape) is not tuple
        or len(shape) > MAX_DIMENSIONS
        or not all(type(n) is int and n >= 0 for n in shape)
    ):
        raise _refuse("an array's shape is not a tuple of non-negative ints")
    return shape


def _latin1(text: object, encoding: object = "latin1") -> bytes:
    """`_codecs.encode` as protocols 0-2 use it for bytes: a string to latin-1, nothing else
    (other codecs would let a pickle run arbitrary codec machinery)."""
    if (
        type(text) is not str
        or type(encoding) is not str
        or codecs.lookup(encoding).name != "iso8859-1"
    ):
        raise _refuse("_codecs.encode is read only for latin-1 text")
    return text.encode("latin1")


def _empty_bytes(*args: object) -> bytes:
    """`bytes()` as protocols 0-2 write an empty bytes object: no arguments."""
    if args:
        raise _refuse("bytes is read only as bytes()")
    return b""


#: Every name a release file may hold, module by module, and what it stands for.
ALLOWED_GLOBALS: dict[tuple[str, str], str] = {
    ("numpy", "ndarray"): "ndarray",
    ("numpy", "dtype"): "dtype",
    ("_codecs", "encode"): "encode",
    ("__builtin__", "bytes"): "bytes",
    ("builtins", "bytes"): "bytes",
    **{
        (f"{core}.{module}", name): name.lstrip("_")
        for core in ("numpy.core", "numpy._core")
        for module, name in (
            ("multiarray", "_reconstruct"),
            ("multiarray", "scalar"),
            ("numeric", "_frombuffer"),
        )
    },
}
#: What a loaded batch may hold besides lists, tuples and the arrays and scalars made.
_PLAIN_VALUES = frozenset({int, float, bool, str, bytes, bytearray, type(None)})
_FILLED = frozenset({_Made, _ArrayStandIn, _DtypeStandIn})


class ReleaseUnpickler(pickle.Unpickler):
    """An unpickler that resolves only `ALLOWED_GLOBALS`, makes arrays, dtypes and scalars
    itself from checked state (together at most `budget` bytes of them), and refuses
    out-of-band buffers and persistent ids. `load` returns the batch with its arrays."""

    def __init__(self, file: Any, budget: int) -> None:
        super().__init__(file)
        self._budget = budget
        self._names: dict[str, _Name | _Marker] = {
            "ndarray": _NDARRAY,
            "dtype": _Name(self._dtype, "numpy.dtype"),
            "encode": _Name(_latin1, "_codecs.encode"),
            "bytes": _Name(_empty_bytes, "bytes"),
            "reconstruct": _Name(self._reconstruct, "numpy's _reconstruct"),
            "scalar": _Name(self._scalar, "numpy's scalar"),
            "frombuffer": _Name(self._frombuffer, "numpy's _frombuffer"),
        }

    def find_class(self, module: str, name: str) -> Any:
        """What the allowed `module.name` stands for; RefusedName for any other."""
        found = ALLOWED_GLOBALS.get((module, name))
        if found is None:
            raise RefusedName(f"{module}.{name}")
        return self._names[found]

    def persistent_load(self, pid: Any) -> Any:
        """Always RefusedName: the release's files hold no persistent ids."""
        raise RefusedName("a persistent id")

    def load(self) -> Any:
        """The next pickle's object, each stand-in replaced by the array, dtype or scalar it
        made; UnpicklingError for a stand-in its pickle never built."""
        return _made(super().load())

    def _dtype(self, spec: object, align: object = False, copy: object = True) -> _DtypeStandIn:
        # numpy's pickles spell a dtype by kind and size; a list, tuple or other string would
        # ask numpy for a structured, object or subarray dtype.
        if type(spec) is not str or not PLAIN_DTYPES.fullmatch(spec):
            shown = repr(spec[:40]) if type(spec) is str else f"given a {type(spec).__name__}"
            raise _refuse(f"dtype {shown} is not read; only {PLAIN_DTYPES.pattern}")
        if type(align) not in (bool, int) or type(copy) not in (bool, int):
            raise _refuse("a dtype is read only as numpy pickles it")
        return _DtypeStandIn(spec)

    def _reconstruct(self, subtype: object, shape: object, typecode: object) -> _ArrayStandIn:
        # numpy's pickles reconstruct an empty int8 array and then BUILD it: any other call
        # would ask for memory the file does not hold.
        if (
            subtype is not _NDARRAY
            or type(shape) is not tuple
            or len(shape) != 1
            or type(shape[0]) is not int
            or shape[0] != 0
            or typecode not in (b"b", "b")
        ):
            raise _refuse("arrays are read only as numpy pickles them")
        return _ArrayStandIn(self)

    def _scalar(self, dtype: object, data: object) -> _Made:
        if type(data) is str:  # a Python 2 pickle's bytes, as numpy reads them
            data = data.encode("latin1")
        return _Made(self._array(data, dtype, (), "C", native=True)[()])

    def _frombuffer(self, data: object, dtype: object, shape: object, order: object) -> _Made:
        if type(order) is not str or order not in ("C", "F"):
            raise _refuse("an array's order is not C or F")
        return _Made(self._array(data, dtype, shape, order, native=False))

    def _array(
        self, data: object, dtype: object, shape: object, order: str, native: bool
    ) -> np.ndarray:
        """The array of `shape` and `dtype` whose bytes, in `order`, are exactly `data`: a
        copy, owning its memory (in native byte order if `native`)."""
        dtype = _built_dtype(dtype)
        shape = _shape(shape)
        if type(data) not in (bytes, bytearray):
            raise _refuse("an array's data is not bytes")
        count = math.prod(shape)
        if count * dtype.itemsize != len(data):
            raise _refuse(
                f"an array's data is {len(data)} bytes; a {shape} {dtype} array has "
                f"{count * dtype.itemsize}"
            )
        # A pickle may hand the same bytes to many arrays; each is a copy, so their total is
        # what is bounded.
        self._budget -= len(data)
        if self._budget < 0:
            raise _refuse("its arrays hold more bytes than the file does from the batch on")
        wanted = dtype.newbyteorder("=") if native else dtype
        return (
            np.frombuffer(data, dtype, count).reshape(shape, order=order).astype(wanted, order="K")
        )


def _made(loaded: Any) -> Any:
    """`loaded` with each stand-in in it (in lists and tuples, at any depth, shared or in
    cycles) replaced by what it made. Lists are changed in place; a tuple holding a stand-in,
    or such a tuple, is replaced by a new one."""
    kind = type(loaded)
    if kind in _FILLED:
        return _value(loaded)
    if kind is not list and kind is not tuple:
        if kind not in _PLAIN_VALUES:
            raise _refuse(f"a batch holds a {kind.__name__}")
        return loaded
    # Every list and tuple is kept here until the end, so no id is reused while ids are keys.
    seen: dict[int, list | tuple] = {id(loaded): loaded}
    tuples: list[tuple] = []
    lists_with_tuples: list[list] = []
    waiting: list[list | tuple] = [loaded]
    while waiting:
        container = waiting.pop()
        is_list = type(container) is list
        if not is_list:
            tuples.append(container)
        holds_tuples = False
        for index, item in enumerate(container):
            kind = type(item)
            if kind in _FILLED:
                if is_list:
                    container[index] = _value(item)
                else:
                    _value(item)  # a stand-in never built is refused wherever it is
            elif kind is list or kind is tuple:
                holds_tuples = holds_tuples or kind is tuple
                if id(item) not in seen:
                    seen[id(item)] = item
                    waiting.append(item)
            elif kind not in _PLAIN_VALUES:
                raise _refuse(f"a batch holds a {kind.__name__}")
        if is_list and holds_tuples:
            lists_with_tuples.append(container)
    if not tuples:
        return loaded
    replaced = _replaced_tuples(tuples)
    for container in lists_with_tuples:
        for index, item in enumerate(container):
            if type(item) is tuple:
                container[index] = replaced[id(item)]
    return replaced[id(loaded)] if type(loaded) is tuple else loaded


def _replaced_tuples(tuples: list[tuple]) -> dict[int, tuple]:
    """Each of `tuples` by id: itself, or a new tuple if it holds a stand-in or a tuple that
    is replaced. Tuples only hold tuples made before them, so tuples within tuples are settled
    innermost first."""
    replaced: dict[int, tuple] = {}
    for outer in tuples:
        unsettled = [outer]
        while unsettled:
            top = unsettled[-1]
            if id(top) in replaced:
                unsettled.pop()
                continue
            inner = [x for x in top if type(x) is tuple and id(x) not in replaced]
            if inner:
                unsettled.extend(inner)
                continue
            unsettled.pop()
            items = tuple(
                _value(x) if type(x) in _FILLED else replaced[id(x)] if type(x) is tuple else x
                for x in top
            )
            changed = any(new is not old for new, old in zip(items, top, strict=True))
            replaced[id(top)] = items if changed else top
    return replaced


def _value(stand_in: _StandIn) -> Any:
    if stand_in.value is None:
        raise _refuse(f"a {stand_in._what()} is named but never built")
    return stand_in.value


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
    (nothing it names is called), a batch cut short, or one that is not a pickle of the
    release's kind. The iterator keeps no reference to a batch it has handed out: a caller that
    drops one frees it before the next is read.
    """
    path = store.path(relative)
    with store.fs.open_input_stream(path) as stream:
        size = store.fs.get_file_info(path).size
        source = io.BufferedReader(_Source(stream), READ_BUFFER)
        yield from read_pickles(source, f"{store.uri}/{relative}", size)


def read_pickles(
    source: io.BufferedReader, shown: str, size: int
) -> Iterator[tuple[int, int, Any]]:
    """`read_batches` of a stream of `size` bytes, open at its start, named `shown` in errors.

    A batch's arrays and scalars together hold at most the bytes from the batch's offset to
    the end of the file: a pickle may hand the same bytes to many arrays, and each is a copy.
    """
    batch = 0
    while True:
        offset = source.tell()
        if not source.peek(1):
            return
        yield batch, offset, _load(source, f"{shown} batch {batch}", offset, size - offset)
        batch += 1


def _load(source: io.BufferedReader, shown: str, offset: int, budget: int) -> Any:
    """One batch's object, read at `offset`; ReleaseFileError saying why it cannot be."""
    try:
        return ReleaseUnpickler(source, budget).load()
    except RefusedName as exc:
        raise ReleaseFileError(
            f"{shown} names {exc.name}; only numpy arrays and lists are read"
        ) from None
    except OSError:
        raise  # the store failed, not the file
    except Exception as exc:
        # A damaged or crafted batch can fail anywhere in the unpickler or numpy, in any
        # exception; each is the file's fault and ends the import in one line.
        if not source.peek(1):
            raise ReleaseFileError(
                f"{shown} at byte {offset} is cut short: the file ends inside it, at byte "
                f"{source.tell()}"
            ) from None
        raise ReleaseFileError(
            f"{shown} at byte {offset} is not a readable pickle: {_reason(exc)}"
        ) from None


def _reason(exc: Exception) -> str:
    """Why a batch failed, in one line of at most about 200 characters."""
    if isinstance(exc, MemoryError):
        return "it asks for more memory than there is"
    if isinstance(exc, RecursionError):
        return "it is nested too deeply"
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else f"{text[:200]}..."
