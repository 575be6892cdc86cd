"""The release unpickler against crafted and damaged pickles: numpy's own `__setstate__` is
never reached (a dtype given numpy's object flags, fields, a subarray; an array given a shape
its bytes do not fill), `numpy.ndarray` is never called, a crash, an allocation the file does
not hold, a recursion or an overflow is a one-line ReleaseFileError, and real arrays and
scalars of every protocol load as `pickle.loads` loads them. Then thousands of mutated release
batches, in a child process whose address space is bounded."""

from __future__ import annotations

import io
import json
import os
import pickle
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import links_ray
from links_ray.data.store import Store
from links_ray.release import pickles
from links_ray.release.pickles import ReleaseFileError, read_batches

try:  # numpy 2 keeps its internals in numpy._core; numpy 1 in numpy.core
    from numpy._core import multiarray, numeric
except ImportError:  # pragma: no cover - numpy 1
    from numpy.core import multiarray, numeric  # type: ignore[no-redef]

#: The checkout whose links_ray these tests import, for the child processes they start.
CHECKOUT = Path(links_ray.__file__).resolve().parents[1]
#: numpy's state of a plain little-endian float64 dtype.
FLOAT64 = (3, "<", None, None, None, -1, -1, 0)

#: 126 bytes: a float64 dtype whose BUILD gives numpy's "list pickle, needs init" flags (10),
#: then an array whose BUILD gives it with a shape of 2**20 and an empty list: numpy's own
#: `__setstate__` took the object-array path and read list items that are not there (SIGSEGV).
OBJECT_FLAGS_PICKLE = b"".join(
    [
        b"\x80\x02",
        b"cnumpy._core.multiarray\n_reconstruct\n",
        b"cnumpy\nndarray\n",
        b"K\x00\x85C\x01b\x87R",  # _reconstruct(ndarray, (0,), b"b")
        b"(K\x01J\x00\x00\x10\x00\x85",  # (1, (2**20,),
        b"cnumpy\ndtype\nX\x02\x00\x00\x00f8\x89\x88\x87R",  # dtype("f8", False, True)
        b"(K\x03X\x01\x00\x00\x00<NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x0atb",  # flags 10
        b"\x89]tb.",  # False, []) BUILD
    ]
)

#: Reads `dataset` of the folder argv[1] in a child that may map argv[2] bytes more than it
#: has once imported (0: no bound); prints the refusal, or "loaded".
READ_IN_CHILD = """
import resource, sys
from pathlib import Path
from links_ray.release.pickles import ReleaseFileError, read_batches
from links_ray.data.store import Store

extra = int(sys.argv[2])
if extra:
    mapped = int(Path("/proc/self/status").read_text().split("VmSize:")[1].split()[0]) * 1024
    resource.setrlimit(resource.RLIMIT_AS, (mapped + extra, resource.RLIM_INFINITY))
try:
    for _ in read_batches(Store.open(sys.argv[1], writable=False), "dataset"):
        pass
except ReleaseFileError as exc:
    print(exc)
else:
    print("loaded")
"""


class Call:
    """Pickles as `func(*args)`, then, if `state` is given, a BUILD with it."""

    def __init__(self, func: Any, args: tuple, state: Any = None) -> None:
        self.func, self.args, self.state = func, args, state

    def __reduce__(self) -> tuple:
        return (self.func, self.args) if self.state is None else (self.func, self.args, self.state)


def dtype(spec: str = "f8", state: tuple = FLOAT64) -> Call:
    return Call(np.dtype, (spec, False, True), state)


def array(shape: Any, of: Any, data: Any, fortran: bool = False) -> Call:
    """An array as numpy pickles one: `_reconstruct`, then a BUILD with its state."""
    return Call(multiarray._reconstruct, (np.ndarray, (0,), b"b"), (1, shape, of, fortran, data))


def child_env() -> dict[str, str]:
    paths = [str(CHECKOUT), os.environ.get("PYTHONPATH", "")]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(path for path in paths if path)}


def read(folder: Path, data: bytes) -> list:
    """Every batch of `data` as the release's `dataset`, read as the import reads it."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "dataset").write_bytes(data)
    store = Store.open(str(folder), writable=False)
    return [value for _, _, value in read_batches(store, "dataset")]


def refusal(folder: Path, data: bytes) -> str:
    """The one-line ReleaseFileError reading `data` raises."""
    with pytest.raises(ReleaseFileError) as refused:
        read(folder, data)
    message = str(refused.value)
    assert "\n" not in message
    assert message.startswith(f"{folder}/dataset batch 0")
    return message


def read_in_child(folder: Path, data: bytes, extra_bytes: int) -> str:
    """What a child process reading `data` prints; the child must exit normally."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "dataset").write_bytes(data)
    result = subprocess.run(
        [sys.executable, "-c", READ_IN_CHILD, str(folder), str(extra_bytes)],
        capture_output=True,
        text=True,
        timeout=300,
        env=child_env(),
    )
    assert result.returncode == 0, f"exit {result.returncode}: {result.stderr[-2000:]}"
    return result.stdout


def test_a_126_byte_pickle_that_crashed_numpy_is_refused_in_one_line(tmp_path: Path) -> None:
    assert len(OBJECT_FLAGS_PICKLE) == 126
    release = tmp_path / "release"
    release.mkdir()
    (release / "dataset").write_bytes(OBJECT_FLAGS_PICKLE)
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "links_ray.cli",
            "import-release",
            str(release),
            "--out",
            str(tmp_path / "root"),
        ],
        capture_output=True,
        text=True,
        timeout=600,
        env=child_env(),
    )
    assert result.returncode == 2, f"exit {result.returncode} (a signal is negative)"
    assert result.stderr.count("\n") == 1
    assert result.stderr.startswith(
        f"links import-release: error: {release}/dataset batch 0 at byte 0 is not a readable "
        "pickle: a f8 dtype's state is not numpy's for a plain dtype"
    )


def test_a_shape_of_2_27_is_refused_without_allocating_it(tmp_path: Path) -> None:
    # numpy's object path allocated the BUILD's shape, 1 GiB, before it read the list: the
    # child may map only 512 MiB more than it has.
    flags = (3, "<", None, None, None, -1, -1, 10)
    data = pickle.dumps(array((2**27,), dtype(state=flags), []), protocol=2)
    assert len(data) < 200
    printed = read_in_child(tmp_path, data, 512 * 2**20)
    assert printed.count("\n") == 1
    assert "is not a readable pickle: a f8 dtype's state is not numpy's" in printed


#: The opcode filter's refusal of a dict, before the unpickler reads it.
NO_DICT = "(b'}') at byte"


@pytest.mark.parametrize(
    ("state", "refused"),
    [
        # Fields and metadata are dicts: the filter refuses them before a dtype sees them.
        pytest.param((3, "|", None, ("a",), {"a": (dtype(), 0)}, 8, 1, 16), NO_DICT, id="fields"),
        pytest.param(
            (3, "<", (dtype(), (2**20,)), None, None, -1, -1, 0),
            "not numpy's for a plain dtype",
            id="subarray",
        ),
        pytest.param((4, "<", None, None, None, -1, -1, 0, {"unit": "m"}), NO_DICT, id="metadata"),
        pytest.param(
            (3, "<", None, None, None, -1, -1, 2**70), "not numpy's for a plain dtype", id="flags"
        ),
    ],
)
def test_a_dtype_state_with_fields_a_subarray_metadata_or_flags_is_refused(
    tmp_path: Path, state: tuple, refused: str
) -> None:
    data = pickle.dumps([array((1,), dtype(state=state), bytes(8))], protocol=2)
    assert refused in refusal(tmp_path, data)


def test_data_that_is_not_exactly_the_shape_s_bytes_is_refused(tmp_path: Path) -> None:
    crafted = {
        "a scalar with bytes after its own": pickle.dumps(
            Call(multiarray.scalar, (dtype(), bytes(16))), protocol=2
        ),
        "an array one byte short": pickle.dumps(array((4,), dtype(), bytes(31)), protocol=2),
        "an array one byte long": pickle.dumps(array((4,), dtype(), bytes(33)), protocol=2),
        "a protocol 5 array eight bytes long": pickle.dumps(
            Call(numeric._frombuffer, (bytearray(40), dtype(), (4,), "C")), protocol=5
        ),
    }
    for name, data in crafted.items():
        message = refusal(tmp_path / name.replace(" ", "_"), data)
        assert "bytes; a " in message, name


def test_numpy_ndarray_is_never_called(tmp_path: Path) -> None:
    called = pickle.dumps([Call(np.ndarray, ((3,), "f8"))], protocol=2)
    assert "numpy.ndarray is never called" in refusal(tmp_path / "reduce", called)
    # NEWOBJ would call the class's __new__: the filter refuses it before the unpickler reads it.
    newobj = b"\x80\x02cnumpy\nndarray\nK\x03\x85\x85\x81."  # ndarray.__new__(ndarray, (3,))
    assert "opcode NEWOBJ (b'\\x81') at byte 21 is not read" in refusal(tmp_path / "newobj", newobj)
    built = b"\x80\x02cnumpy\nndarray\nNb."
    assert "numpy.ndarray takes no BUILD" in refusal(tmp_path / "build", built)


def test_recursion_overflow_and_memory_errors_are_one_line_refusals(tmp_path: Path) -> None:
    def nested_spec(depth: int) -> bytes:
        return b"\x80\x02cnumpy\ndtype\n" + b"]" * depth + b"a" * (depth - 1) + b"\x85R."

    huge_item = (3, "<", None, None, None, 2**70, -1, 0)
    overflow = pickle.dumps(array((1,), dtype(state=huge_item), bytes(8)), protocol=2)
    # BINBYTES8 of 2**50 bytes: the unpickler would have allocated them before reading.
    too_large = b"\x80\x04\x8e" + (2**50).to_bytes(8, "little") + b"data."
    assert "a dtype is given a list" in refusal(tmp_path / "recursion", nested_spec(5_000))
    # A nested list takes more than a hundred bytes for its two, with what finding the arrays
    # in it takes: a million nested exceed the budget.
    depth = 1_000_000
    deep = b"\x80\x02" + b"]" * depth + b"a" * (depth - 1) + b"."
    budget = 64 * len(deep) + 2**20
    assert refusal(tmp_path / "deep", deep).endswith(
        f"is not a readable pickle: its objects would take more than {budget:,} bytes of memory, "
        f"the budget of a file of {len(deep):,} bytes (64 a byte and 1,048,576)"
    )
    assert "not numpy's for a plain dtype" in refusal(tmp_path / "overflow", overflow)
    assert "is cut short: the file ends inside it, at byte 16" in refusal(
        tmp_path / "memory", too_large
    )


def real_values() -> list:
    """Every kind of array and scalar a release file may hold, and plain values around them."""
    square = np.arange(12, dtype=np.float64).reshape(3, 4) / 7
    return [
        square.astype(np.float32),
        square,
        np.asfortranarray(square),
        square[:, ::2],  # neither C nor Fortran: pickled as a C-order copy
        square.astype(">f8"),
        np.asfortranarray(square.astype(">f4")),
        np.arange(5, dtype=np.int64),
        np.arange(5, dtype=np.int32),
        np.arange(5, dtype=">i4"),
        np.arange(5, dtype=np.uint8),
        np.arange(5, dtype=np.uint64),
        np.array([True, False, True]),
        np.array([b"ab", b"c", b""]),
        np.array(2.5),
        np.array(b"xyz"),
        np.zeros(0),
        np.zeros((2, 0, 3), dtype=np.float32, order="F"),
        np.zeros(0, dtype="S3"),
        np.random.default_rng(0).random((40, 200, 2), dtype=np.float32),  # > 1000 bytes
        np.float32(1.25),
        np.float64(-3.5),
        np.int64(-7),
        np.uint16(9),
        np.bool_(True),
        np.bytes_(b"ab"),
        (np.int32(3), [np.zeros(2), 1, 2.5, "text", b"raw", None, True]),
    ]


def assert_same(got: Any, want: Any) -> None:
    assert type(got) is type(want), (got, want)
    if isinstance(want, list | tuple):
        assert len(got) == len(want)
        for inner_got, inner_want in zip(got, want, strict=True):
            assert_same(inner_got, inner_want)
    elif isinstance(want, np.ndarray):
        assert (got.dtype.str, got.shape) == (want.dtype.str, want.shape)
        assert got.flags.f_contiguous == want.flags.f_contiguous
        assert got.flags.c_contiguous == want.flags.c_contiguous
        assert got.flags.writeable and got.flags.owndata
        assert got.tobytes("A") == want.tobytes("A")
    elif isinstance(want, np.generic):
        assert got.dtype.str == want.dtype.str and got.tobytes() == want.tobytes()
    else:
        assert got == want


def test_real_arrays_and_scalars_of_every_protocol_load_as_pickle_loads_them(
    tmp_path: Path,
) -> None:
    values = real_values()
    for protocol in range(6):
        for memo in (True, False):
            pickler_data = []
            for batch in (values, values[:3]):
                stream = io.BytesIO()
                pickler = pickle.Pickler(stream, protocol=protocol)
                pickler.fast = not memo
                pickler.dump(batch)
                pickler_data.append(stream.getvalue())
            data = b"".join(pickler_data)
            files = {"": data}
            if protocol <= 2:  # numpy 1's module names
                files["numpy1"] = data.replace(b"numpy._core.", b"numpy.core.")
            for name, written in files.items():
                folder = tmp_path / f"p{protocol}{'' if memo else '_fast'}{name}"
                got = read(folder, written)
                want = [pickle.loads(part) for part in pickler_data]
                assert_same(got, want)


def test_arrays_in_shared_nested_and_cyclic_structures_are_in_place(tmp_path: Path) -> None:
    shared = np.arange(3.0)
    cyclic: list = [shared]
    cyclic.append(cyclic)
    inner: list = []
    through_tuple = (inner, np.ones(2))
    inner.append(through_tuple)
    batch = [shared, shared, cyclic, through_tuple, ((np.zeros(1),),)]
    (got,) = read(tmp_path / "structures", pickle.dumps(batch, protocol=4))
    assert got[0] is got[1] and isinstance(got[0], np.ndarray)
    assert got[2][0] is got[0] and got[2][1] is got[2]
    assert got[3][0][0] is got[3] and isinstance(got[3][1], np.ndarray)
    assert isinstance(got[4][0][0], np.ndarray)
    # An array at the bottom of 1,000 lists, and of 1,000 tuples (a million are refused: each
    # takes a hundred times its byte or more; test_recursion_overflow_and_memory_errors...).
    depth = 1_000
    leaf = pickle.dumps(np.arange(2.0), protocol=2)[2:-1]  # its opcodes, no PROTO or STOP
    in_lists = b"\x80\x02" + b"]" * depth + leaf + b"a" * depth + b"."
    in_tuples = b"\x80\x02" + leaf + b"\x85" * depth + b"."
    for name, data in (("lists", in_lists), ("tuples", in_tuples)):
        (value,) = read(tmp_path / name, data)
        for _ in range(depth):
            (value,) = value
        np.testing.assert_array_equal(value, np.arange(2.0))


def test_an_array_its_pickle_never_builds_is_refused(tmp_path: Path) -> None:
    unbuilt = pickle.dumps([Call(multiarray._reconstruct, (np.ndarray, (0,), b"b"))], protocol=2)
    assert "an array is named but never built" in refusal(tmp_path, unbuilt)


def test_a_build_of_a_name_or_of_a_made_value_is_refused(tmp_path: Path) -> None:
    # A BUILD on the name itself would have set attributes of the function it stood for.
    of_name = b"\x80\x02cnumpy\ndtype\nK\x01b."
    assert "numpy.dtype takes no BUILD" in refusal(tmp_path / "name", of_name)
    of_scalar = pickle.dumps(Call(multiarray.scalar, (dtype(), bytes(8))), protocol=2)
    of_scalar = of_scalar[:-1] + b"Nb."
    assert "an array or scalar made by a name takes no BUILD" in refusal(
        tmp_path / "scalar", of_scalar
    )
    # Without a memo: a memo's PUTs repeated are out of order, refused by the filter.
    written = io.BytesIO()
    pickler = pickle.Pickler(written, protocol=2)
    pickler.fast = True
    pickler.dump(array((1,), dtype(), bytes(8)))
    once = written.getvalue()
    state = once[once.index(b"(K\x01K\x01\x85") : once.rindex(b"b.")]  # MARK ... TUPLE
    twice = once[:-1] + state + b"b."
    assert "an array is built twice" in refusal(tmp_path / "twice", twice)


def test_arrays_may_not_hold_more_bytes_than_the_budget(tmp_path: Path) -> None:
    # One MiB of bytes in the file, handed by the memo to 96 arrays, each a copy: the budget
    # is 64 bytes a byte of the file and 1 MiB.
    data = bytes(2**20)
    batch = [array((2**17,), dtype(), data) for _ in range(96)]
    pickled = pickle.dumps(batch, protocol=4)
    message = refusal(tmp_path, pickled)
    budget = 64 * len(pickled) + 2**20
    assert message.endswith(
        f"is not a readable pickle: its objects would take more than {budget:,} bytes of "
        f"memory, the budget of a file of {len(pickled):,} bytes (64 a byte and 1,048,576)"
    )
    # Thirty-two copies are within it.
    (got,) = read(tmp_path / "within", pickle.dumps(batch[:32], protocol=4))
    assert len(got) == 32 and all(len(value) == 2**17 for value in got)


def test_dicts_sets_and_bare_names_in_a_batch_are_refused(tmp_path: Path) -> None:
    dicts_and_sets = {
        "EMPTY_DICT": pickle.dumps([{}], 4),
        "SETITEM": b"\x80\x02]K\x01K\x02s.",
        "DICT": pickle.dumps([{"a": 1}], 0),
        "SETITEMS": b"\x80\x04]\x94(K\x01K\x02u.",
        "EMPTY_SET": pickle.dumps([{1}], 4),
        "ADDITEMS": b"\x80\x04](K\x01\x90.",
        "FROZENSET": pickle.dumps([frozenset({1})], 4),
    }
    for name, data in dicts_and_sets.items():
        message = refusal(tmp_path / name, data)
        assert f"opcode {name} " in message and "hold no dict or set" in message, message
    assert "a batch holds a numpy.ndarray" in refusal(
        tmp_path / "name", pickle.dumps([np.ndarray], 2)
    )
    assert "a batch holds a dtype" in refusal(tmp_path / "dtype", pickle.dumps([dtype()], 2))


def test_a_refused_name_is_shown_on_one_line(tmp_path: Path) -> None:
    # STACK_GLOBAL takes any two strings from the file.
    name = "line one\nline two " + "x" * 500
    text = name.encode()
    data = b"\x80\x04\x8c\x02os\x8d" + len(text).to_bytes(8, "little") + text + b"\x93."
    message = refusal(tmp_path, data)
    assert message.endswith("; only numpy arrays and lists are read")
    assert len(message) < len(str(tmp_path)) + 250


def test_mutated_release_batches_load_or_are_refused_in_one_line() -> None:
    cases = 10_000
    result = subprocess.run(
        [sys.executable, "-m", "tests.support.fuzz_release_pickles", "--cases", str(cases)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=CHECKOUT,
        env=child_env(),
    )
    assert result.returncode in (0, 1), f"exit {result.returncode}: {result.stderr[-2000:]}"
    report = json.loads(result.stdout)
    print(json.dumps({k: v for k, v in report.items() if k != "most common refusals"}))
    assert report["violations"] == [] and report["violation"] == 0
    assert result.returncode == 0
    outcomes = (
        "loaded_same",
        "loaded_different",
        "refused_name",
        "refused_cut_short",
        "refused_content",
    )
    assert sum(report[kind] for kind in outcomes) == cases
    assert all(report[kind] > 0 for kind in outcomes)


def test_a_dict_keyed_by_a_deeply_nested_tuple_is_refused(tmp_path: Path) -> None:
    # CPython's C unpickler hashes a dict key at SETITEM (a set item at ADDITEMS), and a
    # tuple's hash recurses with no depth check: a key nested a million deep overflowed the C
    # stack. The filter refuses the dict before the unpickler reads it.
    depth = 1_000_000
    data = b"\x80\x02}" + b")" + b"\x85" * depth + b"Ns."  # {((((),),),...): None}
    printed = read_in_child(tmp_path, data, 0)
    assert printed.count("\n") == 1
    assert (
        "batch 0 at byte 0 is not a readable pickle: opcode EMPTY_DICT (b'}') at byte 2" in printed
    )
    as_set = b"\x80\x04\x8f(" + b")" + b"\x85" * depth + b"\x90."  # {((((),),),...)}
    printed = read_in_child(tmp_path / "set", as_set, 0)
    assert "opcode EMPTY_SET (b'\\x8f') at byte 2" in printed


def test_a_memo_index_near_2_30_is_refused_without_allocating_its_table(tmp_path: Path) -> None:
    # The unpickler sized its memo table by the index, 16 GiB for one near 2**30: the child
    # may map only 256 MiB more than it has.
    long_binput = b"\x80\x02]r\x00\x00\x00\x40."
    printed = read_in_child(tmp_path / "binary", long_binput, 256 * 2**20)
    assert printed.count("\n") == 1
    assert (
        "batch 0 at byte 0 is not a readable pickle: opcode LONG_BINPUT (b'r') at byte 3 puts a "
        "memo index other than the next, 0"
    ) in printed
    put = b"(lp1073741823\n."
    printed = read_in_child(tmp_path / "text", put, 256 * 2**20)
    assert "opcode PUT (b'p') at byte 2 puts a memo index other than the next, 0" in printed


def test_memo_indices_out_of_order_are_refused(tmp_path: Path) -> None:
    crafted = {
        "put": (b"\x80\x02]q\x00]q\x02e.", "opcode BINPUT (b'q') at byte 6 puts a memo index"),
        "get": (b"\x80\x02]q\x00h\x01a.", "opcode BINGET (b'h') at byte 5 gets a memo index"),
    }
    for name, (data, refused) in crafted.items():
        assert refused in refusal(tmp_path / name, data)


def test_a_refusal_in_a_later_batch_names_that_batch(tmp_path: Path) -> None:
    first = pickle.dumps([np.arange(3.0)], 4)
    second = pickle.dumps([np.arange(2)], 4)
    for name, data, batch, at in (
        ("in it", first + second[:-2] + b"}" + second[-2:], 1, len(first) + len(second) - 2),
        ("where it begins", first + b"}.", 1, len(first)),
        ("after two", first + second + b"\x8f.", 2, len(first) + len(second)),
    ):
        folder = tmp_path / name.replace(" ", "_")
        (folder / "release").mkdir(parents=True)
        (folder / "release" / "dataset").write_bytes(data)
        read = []
        with pytest.raises(ReleaseFileError) as refused:
            for _, _, value in read_batches(Store.open(str(folder / "release")), "dataset"):
                read.append(value)
        assert len(read) == batch
        offset = len(first) if batch == 1 else len(first) + len(second)
        assert str(refused.value).startswith(
            f"{folder}/release/dataset batch {batch} at byte {offset} is not a readable pickle: "
            f"opcode "
        )
        assert f" at byte {at} is not read" in str(refused.value)


@pytest.mark.parametrize("buffer", [1, 2, 3, 7, 64, 1000])
def test_reads_of_any_size_give_the_same_batches_and_refusals(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, buffer: int
) -> None:
    # The filter sees the file in the reads the buffered reader makes, as small as these.
    monkeypatch.setattr(pickles, "READ_BUFFER", buffer)
    values = real_values()
    for protocol in range(6):
        batches = [pickle.dumps(values, protocol), pickle.dumps(values[:3], protocol)]
        got = read(tmp_path / f"p{protocol}", b"".join(batches))
        assert_same(got, [pickle.loads(batch) for batch in batches])
        refused = batches[0] + batches[1][:-1] + b"h\x7f."
        with pytest.raises(ReleaseFileError) as raised:
            read(tmp_path / f"refused{protocol}", refused)
        message = str(raised.value)
        assert message.startswith(f"{tmp_path}/refused{protocol}/dataset batch 1 ")
        assert f"opcode BINGET (b'h') at byte {len(refused) - 3} gets a memo index" in message
