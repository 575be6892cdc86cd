"""The grammar of the release pickle fuzzer (`bench.pickle_fuzz`): a Hypothesis strategy
(`pickles`) of release-file-shaped bytes, built opcode by opcode.

A value is None, a bool, an int of any width, a float, a string (short, 4- and 8-byte lengths,
protocol 0's text, some widened by one wide character), bytes or a bytearray, latin-1 bytes
through `_codecs.encode`, a list or tuple of any of its opcodes, a numpy array or scalar as numpy
pickles it (`_reconstruct` and BUILD, `scalar`, `_frombuffer`), a memo GET, a memoized string
encoded again and again, repeats of a GET, and, now and then, an opcode the release never holds
(NEWOBJ, a dict, an extension code) or a BUILD of the wrong thing; values are memoized by PUTs.
A batch is protocol 2 to 5, maybe framed; a file is one to three batches, and a few are damaged
(a byte changed, the end cut).

Hypothesis is imported only when the strategy is made: it is a test dependency.
"""

from __future__ import annotations

import io
import pickle
import pickletools
from collections.abc import Callable
from typing import Any

import numpy as np

#: Opcodes the release never holds, with argument bytes that make them whole.
FOREIGN = (
    b"}",  # EMPTY_DICT
    b"(d",  # MARK DICT
    b"\x8f",  # EMPTY_SET
    b"\x81",  # NEWOBJ
    b"\x92",  # NEWOBJ_EX
    b"o",  # OBJ
    b"ibuiltins\nobject\n",  # INST
    b"\x82\x01",  # EXT1
    b"Pid\n",  # PERSID
    b"Q",  # BINPERSID
    b"\x97",  # NEXT_BUFFER
    b"2",  # DUP
    b"s",  # SETITEM
    b"\x90",  # ADDITEMS
    b"cbuiltins\neval\n",  # a name never allowed
    b"\x8c\x02os\x8c\x06system\x93",  # and by STACK_GLOBAL
)


def _fragment(value: Any, protocol: int) -> bytes:
    """The opcodes that push `value` as a memo-less pickler of `protocol` writes them: no
    PROTO, FRAME or STOP, and no memo (so they fit anywhere in a pickle)."""
    out = io.BytesIO()
    pickler = pickle.Pickler(out, protocol)
    pickler.fast = True
    pickler.dump(value)
    data = out.getvalue()
    ops = list(pickletools.genops(data))
    kept = []
    for (op, _, start), following in zip(ops, [*ops[1:], None], strict=True):
        if op.name in ("PROTO", "FRAME", "STOP"):
            continue
        kept.append(data[start : following[2] if following else len(data)])
    return b"".join(kept)


def _numpy_values(draw: Callable, st: Any) -> Any:
    """A numpy array or scalar of a release's plain dtypes, small."""
    dtype = draw(
        st.sampled_from(["b1", "i1", "u1", "<i2", ">i4", "<u8", "<f2", ">f4", "<f8", "S3"])
    )
    shape = tuple(draw(st.lists(st.integers(0, 4), max_size=3)))
    count = int(np.prod(shape, dtype=np.int64))
    seed = draw(st.integers(0, 2**32 - 1))
    raw = np.random.default_rng(seed).integers(0, 256, count * np.dtype(dtype).itemsize, np.uint8)
    array = np.frombuffer(raw.tobytes(), dtype).reshape(shape)
    if dtype == "b1":
        array = array.astype(bool)
    if draw(st.booleans()):
        array = np.asfortranarray(array)
    if draw(st.integers(0, 4)) == 0:
        return array.reshape(-1)[:1].copy()[0] if count else np.float64(1.5)
    return array


class _Builder:
    """A pickle's opcodes drawn one value at a time, with its memo's next index."""

    def __init__(self, draw: Callable, st: Any, protocol: int) -> None:
        self.draw = draw
        self.st = st
        self.protocol = protocol
        self.memo = 0
        self.strings: list[int] = []  # memo indices of strings
        self.encode: int | None = None  # memo index of _codecs.encode

    def put(self) -> bytes:
        """A memo PUT of the value on top of the stack: usually the next index, now and then
        another (which the filter refuses)."""
        draw = self.draw
        index = self.memo if draw(self.st.integers(0, 30)) else draw(self.st.integers(0, 300))
        self.memo += 1
        how = draw(self.st.integers(0, 3))
        if how == 0 and self.protocol >= 4:
            return pickle.MEMOIZE
        if how == 1:
            return pickle.LONG_BINPUT + index.to_bytes(4, "little")
        if how == 2:
            return pickle.PUT + str(index).encode() + b"\n"
        return pickle.BINPUT + (index % 256).to_bytes(1, "little")

    def get(self, index: int) -> bytes:
        """A memo GET of `index`, in one of its three opcodes."""
        how = self.draw(self.st.integers(0, 2))
        if how == 0:
            return pickle.LONG_BINGET + index.to_bytes(4, "little")
        if how == 1:
            return pickle.GET + str(index).encode() + b"\n"
        return pickle.BINGET + (index % 256).to_bytes(1, "little")

    def string(self) -> bytes:
        """A str in one of its opcodes: drawn text, or a long run of one character with a wide
        one at its end."""
        draw, st = self.draw, self.st
        if draw(st.booleans()):
            text = draw(st.text(max_size=40))
        else:
            text = "a" * draw(st.integers(0, 4000)) + draw(st.sampled_from(["", "é", "€", "😀"]))
        raw = text.encode("utf-8", "surrogatepass")
        how = draw(st.integers(0, 3))
        if how == 0 and len(raw) < 256 and self.protocol >= 4:
            return pickle.SHORT_BINUNICODE + bytes([len(raw)]) + raw
        if how == 1 and self.protocol >= 4:
            return pickle.BINUNICODE8 + len(raw).to_bytes(8, "little") + raw
        if how == 2 and "\n" not in text and "\\" not in text:
            return pickle.UNICODE + text.encode("raw-unicode-escape") + b"\n"
        return pickle.BINUNICODE + len(raw).to_bytes(4, "little") + raw

    def byte_string(self) -> bytes:
        """Bytes or a bytearray in one of their opcodes, or latin-1 bytes made by
        `_codecs.encode`, or `bytes()`."""
        draw, st = self.draw, self.st
        raw = bytes(draw(st.integers(0, 4000))) if draw(st.booleans()) else draw(st.binary())
        how = draw(st.integers(0, 5))
        if how == 0 and len(raw) < 256:
            return pickle.SHORT_BINBYTES + bytes([len(raw)]) + raw
        if how == 1 and self.protocol >= 4:
            return pickle.BINBYTES8 + len(raw).to_bytes(8, "little") + raw
        if how == 2 and self.protocol >= 5:
            return pickle.BYTEARRAY8 + len(raw).to_bytes(8, "little") + raw
        if how == 3:
            text = raw.decode("latin1").encode()
            return (
                b"c_codecs\nencode\n"
                + pickle.BINUNICODE
                + len(text).to_bytes(4, "little")
                + text
                + b"X\x06\x00\x00\x00latin1"
                + pickle.TUPLE2
                + pickle.REDUCE
            )
        if how == 4:
            return b"c__builtin__\nbytes\n" + pickle.EMPTY_TUPLE + pickle.REDUCE
        return pickle.BINBYTES + len(raw).to_bytes(4, "little") + raw

    def number(self) -> bytes:
        """An int, float, bool or None in one of their opcodes."""
        draw, st = self.draw, self.st
        value = draw(st.integers(-(2**70), 2**70))
        how = draw(st.integers(0, 7))
        if how == 0:
            return pickle.BININT1 + (value % 256).to_bytes(1, "little")
        if how == 1:
            return pickle.BININT2 + (value % 65536).to_bytes(2, "little")
        if how == 2:
            return pickle.BININT + (value % 2**32).to_bytes(4, "little")
        if how == 3:
            raw = pickle.encode_long(value)
            return pickle.LONG1 + bytes([len(raw)]) + raw
        if how == 4:
            return pickle.INT + str(value).encode() + b"\n"
        if how == 5:
            return pickle.BINFLOAT + draw(st.binary(min_size=8, max_size=8))
        return draw(st.sampled_from([pickle.NONE, pickle.NEWTRUE, pickle.NEWFALSE]))

    def value(self, depth: int) -> bytes:
        """One value's opcodes, maybe memoized."""
        draw, st = self.draw, self.st
        kinds = ["number", "string", "bytes", "numpy", "get", "encode_again", "foreign"]
        if depth < 3:
            kinds += ["list", "tuple", "list", "tuple", "repeat"]
        if depth == 0:
            kinds += ["amplify", "nest"]
        kind = draw(st.sampled_from(kinds))
        if kind == "amplify":
            made = self.amplify()
        elif kind == "nest":
            made = self.nest()
        elif kind == "number":
            made = self.number()
        elif kind == "string":
            made = self.string()
            if draw(st.booleans()):
                made += self.put()
                self.strings.append(self.memo - 1)
                return made
        elif kind == "bytes":
            made = self.byte_string()
        elif kind == "numpy":
            made = _fragment(_numpy_values(draw, st), self.protocol)
        elif kind == "get":
            made = self.get(draw(st.integers(0, self.memo))) if self.memo else pickle.NONE
        elif kind == "encode_again":
            made = self.encode_again()
        elif kind == "foreign":
            made = draw(st.sampled_from(FOREIGN)) + self.value(depth + 1) + pickle.BUILD
        elif kind == "list":
            made = self.list(depth)
        elif kind == "tuple":
            made = self.tuple(depth)
        else:
            made = self.repeat(depth)
        then = draw(st.integers(0, 119))
        if then % 4 == 0:
            made += self.put()
        if then < 4:  # a BUILD of whatever was made, with any state
            made += self.value(depth + 1) + pickle.BUILD
        return made

    def items(self, depth: int) -> list[bytes]:
        """Up to five values, nested one deeper."""
        return [self.value(depth + 1) for _ in range(self.draw(self.st.integers(0, 5)))]

    def list(self, depth: int) -> bytes:
        """A list by EMPTY_LIST and APPEND or APPENDS, or by MARK and LIST."""
        items = self.items(depth)
        how = self.draw(self.st.integers(0, 2))
        if how == 0:
            return pickle.EMPTY_LIST + b"".join(item + pickle.APPEND for item in items)
        if how == 1:
            return pickle.EMPTY_LIST + pickle.MARK + b"".join(items) + pickle.APPENDS
        return pickle.MARK + b"".join(items) + pickle.LIST

    def tuple(self, depth: int) -> bytes:
        """A tuple by EMPTY_TUPLE, TUPLE1 to TUPLE3 or MARK and TUPLE."""
        items = self.items(depth)
        if len(items) <= 3 and self.draw(self.st.booleans()):
            codes = (pickle.EMPTY_TUPLE, pickle.TUPLE1, pickle.TUPLE2, pickle.TUPLE3)
            return b"".join(items) + codes[len(items)]
        return pickle.MARK + b"".join(items) + pickle.TUPLE

    def encode_again(self) -> bytes:
        """A memoized string encoded to latin-1 once more, the encoder memoized too."""
        if not self.strings:
            return self.byte_string()
        first, again = self._encoder()
        return first + again

    def _encoder(self) -> tuple[bytes, bytes]:
        """(what memoizes `_codecs.encode` first, if it is not yet, and pops it; a memoized
        string's encoding by it)."""
        first = b""
        if self.encode is None:
            self.encode = self.memo
            self.memo += 1
            first = b"c_codecs\nencode\n" + pickle.BINPUT + bytes([self.encode % 256]) + pickle.POP
        index = self.strings[self.draw(self.st.integers(0, len(self.strings) - 1))]
        again = (
            self.get(self.encode)
            + self.get(index)
            + b"X\x06\x00\x00\x00latin1"
            + pickle.TUPLE2
            + pickle.REDUCE
        )
        return first, again

    def amplify(self) -> bytes:
        """A list of a long memoized string and up to 3,000 encodings of it."""
        text = "a" * self.draw(self.st.integers(1000, 20_000))
        string = pickle.BINUNICODE + len(text).to_bytes(4, "little") + text.encode()
        string += self.put()
        self.strings.append(self.memo - 1)
        first, one = self._encoder()
        times = self.draw(self.st.integers(1, 3000))
        return (
            string
            + pickle.POP
            + first
            + pickle.EMPTY_LIST
            + pickle.MARK
            + one * times
            + (pickle.APPENDS)
        )

    def nest(self) -> bytes:
        """Lists or tuples nested up to 300,000 deep."""
        depth = self.draw(self.st.integers(1, 300_000))
        if self.draw(self.st.booleans()):
            return pickle.EMPTY_LIST * depth + pickle.APPEND * (depth - 1)
        return pickle.EMPTY_TUPLE + pickle.TUPLE1 * depth

    def repeat(self, depth: int) -> bytes:
        """A list of one memo-less value repeated up to 3,000 times: a GET, or a memoized
        string encoded again (so a few bytes each make a copy of it)."""
        times = self.draw(self.st.integers(1, 3000))
        if self.strings and self.draw(self.st.booleans()):
            first, one = self._encoder()
        else:
            first, one = b"", self.get(self.memo // 2) if self.memo else pickle.NONE
        return first + pickle.EMPTY_LIST + pickle.MARK + one * times + pickle.APPENDS


def pickles() -> Any:
    """A Hypothesis strategy of release-file-shaped bytes: one to three batches of protocol 2
    to 5 from the grammar, some framed, a few damaged."""
    from hypothesis import strategies as st

    @st.composite
    def files(draw: Callable) -> bytes:
        batches = []
        for _ in range(draw(st.integers(1, 3))):
            protocol = draw(st.integers(2, 5))
            body = _Builder(draw, st, protocol).value(0)
            if protocol >= 4 and draw(st.booleans()):
                length = len(body) + 1 if draw(st.integers(0, 9)) else draw(st.integers(0, 2**40))
                body = pickle.FRAME + length.to_bytes(8, "little") + body
            batches.append(pickle.PROTO + bytes([protocol]) + body + pickle.STOP)
        data = bytearray(b"".join(batches))
        damage = draw(st.integers(0, 9))
        if damage == 0 and data:
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        elif damage == 1:
            del data[draw(st.integers(0, len(data))) :]
        return bytes(data)

    return files()
