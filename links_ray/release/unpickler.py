"""The restricted unpickler of the LINKS release's files: it runs nothing a pickle names.

Unpickling runs whatever callable a pickle names, so `ReleaseUnpickler` resolves only the names
a plain `pickle.dump` of lists of numpy arrays and scalars uses (protocols 0 to 5, numpy 1 and
numpy 2 module names) and refuses any other before anything is called. Lists, tuples, ints,
floats, bools and strings need no name at all.

Nor does a pickle reach numpy's own constructors: what it names stands in for code of ours.
A pickle's BUILD step hands state from the file to the object's `__setstate__`, and numpy's
(of an array or a dtype) trusts that state, so the objects the unpickler makes are stand-ins
whose `__setstate__` accepts only the state numpy writes for a plain array: a dtype of the
kinds in `PLAIN_DTYPES`, then a shape and exactly the bytes that shape holds. The array is a
copy of those bytes, made by numpy's buffer constructor; once the pickle is loaded, each
stand-in is replaced by what it made.

Everything it makes is charged to the file's memory ledger (`release.opcode_scan.charge`), each
before it is made: the arrays and scalars, the bytes `_codecs.encode` gives (as many as its
string has characters), the stand-ins, and the bookkeeping of replacing them in the batch. The
filter has charged what the unpickler's opcodes make themselves.

Files are read through it, behind the opcode filter, by `release.pickles`. Pure numpy: no Ray.
"""

from __future__ import annotations

import functools
import gc
import pickle
import re
from collections.abc import Callable
from typing import Any

import numpy as np

from links_ray.release.opcode_scan import charge

#: The dtypes an array or scalar of a release file may have, as numpy's pickles spell them
#: (kind and item size): bool, signed and unsigned ints, floats, and byte strings of any length.
PLAIN_DTYPES = re.compile(r"b1|[iuf][248]|[iu]1|S[1-9][0-9]{0,9}")
#: The most dimensions an array may have (numpy 2's own limit).
MAX_DIMENSIONS = 64
#: The spellings of latin-1 `_codecs.encode` is read with (pickle writes "latin1").
LATIN1 = frozenset({"latin1", "latin-1", "latin_1", "iso8859-1", "iso-8859-1", "l1"})
# What the unpickler's code makes, charged to the ledger (bytes, CPython 3.11's rounded up): a
# stand-in; an array's object with its shape and strides (twice: a view, then the copy); a
# bytes object before its bytes; a list or tuple of the batch as `_made` tracks it (an entry of
# a dict keyed by an int, and of a list), and a tuple it replaces, before its slots.
_STAND_IN_COST = 96
_ARRAY_COST = 2 * 128
_PER_DIMENSION_COST = 2 * 16
_BYTES_COST = 48
_TRACKED_COST = 192
_TUPLE_COST = 160


class RefusedName(pickle.UnpicklingError):
    """A pickle names a global the release's files never hold."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.name = name


def _refuse(why: str) -> pickle.UnpicklingError:
    return pickle.UnpicklingError(why)


@functools.lru_cache(maxsize=256)
def _dtype_states(spec: str) -> tuple[tuple[tuple, np.dtype, np.dtype], ...]:
    """numpy's BUILD states of the plain dtype `spec` (versions 3 and 4, each byte order numpy
    writes for it), each with the dtype it gives and that dtype in native byte order;
    UnpicklingError for a spec not of PLAIN_DTYPES."""
    # A list, a tuple or another string would ask numpy for a structured, object or subarray
    # dtype.
    if not PLAIN_DTYPES.fullmatch(spec):
        raise _refuse(f"dtype {spec[:40]!r} is not read; only {PLAIN_DTYPES.pattern}")
    dtype = np.dtype(spec)
    size, alignment = (dtype.itemsize, 1) if dtype.kind == "S" else (-1, -1)
    orders = "|" if dtype.kind == "S" or dtype.itemsize == 1 else "<>"
    return tuple(
        (state, ordered, ordered.newbyteorder("="))
        for order in orders
        for ordered in (dtype if order == "|" else dtype.newbyteorder(order),)
        for state in (
            (3, order, None, None, None, size, alignment, 0),
            (4, order, None, None, None, size, alignment, 0, None),
        )
    )


class _StandIn:
    """What the unpickler hands a pickle in place of a numpy object: `value` is the object once
    made (None until then). A BUILD of it is refused unless a subclass takes one."""

    __slots__ = ("value",)
    what = "a value"

    def __init__(self, value: Any = None) -> None:
        self.value = value

    def __setstate__(self, state: object) -> None:
        raise _refuse(f"{self.what} made by a name takes no BUILD")


class _Made(_StandIn):
    """An array (protocol 5's `_frombuffer`) or a scalar, made and checked when named."""

    __slots__ = ()
    what = "an array or scalar"


class _DtypeStandIn(_StandIn):
    """`numpy.dtype(spec)`, made when its one BUILD gives one of numpy's `states` of it;
    `native` is the dtype in native byte order."""

    __slots__ = ("native", "spec", "states")
    what = "a dtype"

    def __init__(self, spec: str) -> None:
        self.value: np.dtype | None = None
        self.native: np.dtype | None = None
        self.spec = spec
        self.states = _dtype_states(spec)

    def __setstate__(self, state: object) -> None:
        if self.value is not None:
            raise _refuse("a dtype is built twice")
        # Equality with numpy's own states: those are tuples of ints, strings and None, so
        # comparing one with the file's never descends into the file's data.
        for known, dtype, native in self.states:
            if state == known:
                self.value = dtype
                self.native = native
                return
        raise _refuse(
            f"a {self.spec} dtype's state is not numpy's for a plain dtype (no fields, "
            "subarray, metadata or flags; numpy's item size, alignment and byte order)"
        )


class _ArrayStandIn(_StandIn):
    """numpy's `_reconstruct` result: an array made when its one BUILD gives numpy's state of
    it, `(1, shape, dtype, is_fortran, data)`."""

    __slots__ = ("_maker",)
    what = "an array"

    def __init__(self, maker: _Maker) -> None:
        self.value = None
        self._maker = maker

    def __setstate__(self, state: object) -> None:
        if self.value is not None:
            raise _refuse("an array is built twice")
        if type(state) is not tuple or len(state) != 5:
            raise _refuse("an array's state is not numpy's (version, shape, dtype, order, data)")
        version, shape, dtype, is_fortran, data = state
        if version != 1 or is_fortran not in (False, True):
            raise _refuse("an array's state is not numpy's version 1 with a bool order")
        if type(data) is str:  # a Python 2 pickle's bytes, as numpy reads them
            data = self._maker.latin1(data)
        # numpy's own BUILD swaps a non-native array's bytes into native order.
        order = "F" if is_fortran else "C"
        self.value = self._maker.array(data, dtype, shape, order, native=True)


class _Marker:
    """`numpy.ndarray` as a pickle names it: nothing to call, only the subtype that
    `_reconstruct` is given."""

    __slots__ = ()

    def __call__(self, *args: object) -> None:
        raise _refuse("numpy.ndarray is never called; arrays are read only as numpy pickles them")

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
#: What a loaded batch may hold besides lists, tuples and the arrays and scalars made (not a
#: dtype on its own).
_PLAIN_VALUES = frozenset({int, float, bool, str, bytes, bytearray, type(None)})
_STAND_INS = frozenset({_Made, _ArrayStandIn})
#: The largest extent of an array's dimension.
_MAX_EXTENT = np.iinfo(np.intp).max


class _Maker:
    """The arrays, dtypes, scalars and bytes of one pickle, made from checked state, each
    charged to the file's ledger `ledger` (a `release.opcode_scan` state) before it is made."""

    __slots__ = ("ledger",)

    def __init__(self, ledger: np.ndarray) -> None:
        self.ledger = ledger

    def latin1(self, text: object, encoding: object = "latin1") -> bytes:
        """`_codecs.encode` as protocols 0-2 use it for bytes: a string to latin-1, nothing
        else (other codecs would let a pickle run arbitrary codec machinery)."""
        if type(text) is not str or type(encoding) is not str or encoding not in LATIN1:
            raise _refuse("_codecs.encode is read only for latin-1 text")
        # Latin-1 gives a byte a character: a string from the memo, encoded again and again,
        # is charged each time before it is.
        charge(self.ledger, _BYTES_COST + len(text))
        return text.encode("latin1")

    def array(
        self, data: object, dtype: object, shape: object, order: str, native: bool
    ) -> np.ndarray:
        """The array of `shape` and `dtype` (a built dtype stand-in) whose bytes, in `order`,
        are exactly `data`: a copy owning its memory, in native byte order if `native`."""
        if type(dtype) is not _DtypeStandIn or dtype.native is None:
            raise _refuse("an array's dtype is not one the pickle has built")
        made = dtype.native if native else dtype.value
        if type(shape) is not tuple or len(shape) > MAX_DIMENSIONS:
            raise _refuse(f"an array's shape is not a tuple of at most {MAX_DIMENSIONS} ints")
        count = 1
        for extent in shape:
            if type(extent) is not int or not 0 <= extent <= _MAX_EXTENT:
                raise _refuse("an array's shape holds something other than a size")
            count *= extent
        if type(data) is not bytes and type(data) is not bytearray:
            raise _refuse("an array's data is not bytes")
        size = count * made.itemsize
        if size != len(data):
            raise _refuse(
                f"an array's data is {len(data)} bytes; a {shape} {made} array has {size}"
            )
        # Each array is a copy, and a pickle may hand the same bytes to many: each is charged.
        charge(self.ledger, size + _ARRAY_COST + _PER_DIMENSION_COST * len(shape))
        # Positional (shape, dtype, buffer, offset, strides, order): numpy's keyword parsing
        # takes longer than copying a small array.
        return np.ndarray(shape, dtype.value, data, 0, None, order).astype(made, "K")

    def dtype(self, spec: object, align: object = False, copy: object = True) -> _DtypeStandIn:
        """`numpy.dtype` as numpy's pickles call it, for a spec of PLAIN_DTYPES."""
        if type(spec) is not str:
            raise _refuse(f"a dtype is given a {type(spec).__name__}, not numpy's spec")
        if align not in (False, True) or copy not in (False, True):
            raise _refuse("a dtype is read only as numpy pickles it")
        charge(self.ledger, _STAND_IN_COST)
        return _DtypeStandIn(spec)

    def reconstruct(self, subtype: object, shape: object, typecode: object) -> _ArrayStandIn:
        """numpy's `_reconstruct` as its pickles call it: an array its BUILD then makes."""
        # Any other call would ask for memory the file does not hold.
        if subtype is not _NDARRAY or shape != (0,) or typecode not in (b"b", "b"):
            raise _refuse("arrays are read only as numpy pickles them")
        charge(self.ledger, _STAND_IN_COST)
        return _ArrayStandIn(self)

    def scalar(self, dtype: object, data: object) -> _Made:
        """numpy's `scalar(dtype, data)`: the scalar of a dtype stand-in from its bytes."""
        if type(data) is str:  # a Python 2 pickle's bytes, as numpy reads them
            data = self.latin1(data)
        made = self.array(data, dtype, (), "C", native=True)
        # The scalar is a second copy of the array's bytes.
        charge(self.ledger, _STAND_IN_COST + _ARRAY_COST + made.nbytes)
        return _Made(made[()])

    def frombuffer(self, data: object, dtype: object, shape: object, order: object) -> _Made:
        """numpy's `_frombuffer` (protocol 5): the array of `shape` in `data`."""
        if order not in ("C", "F"):
            raise _refuse("an array's order is not C or F")
        charge(self.ledger, _STAND_IN_COST)
        return _Made(self.array(data, dtype, shape, "F" if order == "F" else "C", native=False))


class ReleaseUnpickler(pickle.Unpickler):
    """An unpickler that resolves only `ALLOWED_GLOBALS`, makes arrays, dtypes and scalars
    itself from checked state, charging all it makes to `ledger` (the scan state of the
    `release.opcode_scan` filter its file passes), and refuses out-of-band buffers and
    persistent ids. `load` returns the batch with its arrays."""

    def __init__(self, file: Any, ledger: np.ndarray) -> None:
        super().__init__(file)
        self._ledger = ledger
        # Nothing the names reach refers back to the unpickler: a cycle would keep its memo,
        # and every array's bytes in it, until the garbage collector ran.
        maker = _Maker(ledger)
        stands_for: dict[str, _Name | _Marker] = {
            "ndarray": _NDARRAY,
            "dtype": _Name(maker.dtype, "numpy.dtype"),
            "encode": _Name(maker.latin1, "_codecs.encode"),
            "bytes": _Name(_empty_bytes, "bytes"),
            "reconstruct": _Name(maker.reconstruct, "numpy's _reconstruct"),
            "scalar": _Name(maker.scalar, "numpy's scalar"),
            "frombuffer": _Name(maker.frombuffer, "numpy's _frombuffer"),
        }
        self._globals = {name: stands_for[role] for name, role in ALLOWED_GLOBALS.items()}

    def find_class(self, module: str, name: str) -> Any:
        """What the allowed `module.name` stands for; RefusedName for any other."""
        found = self._globals.get((module, name))
        if found is None:
            shown = f"{module}.{name}"
            # A name is any string a pickle holds: shown on one line, and not all of it.
            raise RefusedName(
                shown if shown.isprintable() and len(shown) <= 100 else repr(shown[:100])
            )
        return found

    def persistent_load(self, pid: Any) -> Any:
        """Always RefusedName: the release's files hold no persistent ids."""
        raise RefusedName("a persistent id")

    def load(self) -> Any:
        """The next pickle's object, each stand-in replaced by the array or scalar it made;
        UnpicklingError for an array its pickle never built, or a batch holding anything but
        lists, tuples, arrays, scalars and plain values (a dict, a set, a dtype, a name)."""
        # A batch is hundreds of thousands of objects that all live until it is loaded: the
        # garbage collector's passes over them would find nothing, and take longer than the
        # load. Nothing the unpickler makes refers to itself, so none of it waits for one.
        collecting = gc.isenabled()
        gc.disable()
        try:
            loaded = super().load()
        finally:
            if collecting:
                gc.enable()
        return _made(loaded, self._ledger)


def _made(loaded: Any, ledger: np.ndarray) -> Any:
    """`loaded` with each stand-in in it (in lists and tuples, at any depth, shared or in
    cycles) replaced by what it made, the bookkeeping charged to `ledger`. Lists are changed
    in place; a tuple holding a stand-in, or such a tuple, is replaced by a new one."""
    kind = type(loaded)
    if kind in _STAND_INS:
        return _value(loaded)
    if kind is not list and kind is not tuple:
        return _plain(loaded)
    # Every list and tuple stays referenced here until the end, so no id is reused while ids
    # are keys.
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
            if kind in _STAND_INS:
                if is_list:
                    container[index] = _value(item)
                else:
                    _value(item)  # a stand-in never built is refused wherever it is
            elif kind is list or kind is tuple:
                holds_tuples = holds_tuples or kind is tuple
                if id(item) not in seen:
                    # Charged in steps: a charge per container would slow the walk.
                    if len(seen) % 1024 == 1:
                        charge(ledger, 1024 * _TRACKED_COST)
                    seen[id(item)] = item
                    waiting.append(item)
            elif kind not in _PLAIN_VALUES:
                _plain(item)
        if is_list and holds_tuples:
            lists_with_tuples.append(container)
    if not tuples:
        return loaded
    replaced = _replaced_tuples(tuples, ledger)
    for container in lists_with_tuples:
        for index, item in enumerate(container):
            if type(item) is tuple:
                container[index] = replaced[id(item)]
    return replaced[id(loaded)] if type(loaded) is tuple else loaded


def _replaced_tuples(tuples: list[tuple], ledger: np.ndarray) -> dict[int, tuple]:
    """Each of `tuples` by id: itself, or a new tuple if it holds a stand-in or a tuple that
    is replaced, each charged to `ledger`. A tuple holds only tuples made before it, so tuples
    within tuples are settled innermost first."""
    charge(ledger, _TUPLE_COST * len(tuples))
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
            charge(ledger, 8 * len(top))
            items = tuple(
                _value(x) if type(x) in _STAND_INS else replaced[id(x)] if type(x) is tuple else x
                for x in top
            )
            changed = any(new is not old for new, old in zip(items, top, strict=True))
            replaced[id(top)] = items if changed else top
    return replaced


def _value(stand_in: _StandIn) -> Any:
    if stand_in.value is None:
        raise _refuse(f"{stand_in.what} is named but never built")
    return stand_in.value


def _plain(value: Any) -> Any:
    # Dicts and sets, bare names and dtypes are no part of a release file.
    if type(value) not in _PLAIN_VALUES:
        kind = type(value)
        shown = (
            repr(value)
            if kind in (_Name, _Marker)
            else "dtype"
            if kind is _DtypeStandIn
            else kind.__name__
        )
        raise _refuse(f"a batch holds a {shown}; only lists, tuples, numbers, strings and arrays")
    return value
