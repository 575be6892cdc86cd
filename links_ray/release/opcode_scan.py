"""The opcode filter in front of the release unpickler: a scan of a pickle's opcode stream, chunk
by chunk, that stops at the first opcode a release file never holds.

CPython's C unpickler acts on some opcodes before any code of ours sees their result: SETITEM
and ADDITEMS hash their keys (a tuple's hash recurses with no depth check), and PUT sizes the
memo table by the index the file gives. The release's batches are lists of numpy arrays and
scalars written by `pickle.dump`, so the scan allows only the opcodes such pickles and plain
lists, tuples, numbers, strings and bytes use (`ALLOWED`), memo indices in the order the pickler
writes them (each PUT the next index, each GET one already put), and at most `MAX_MARKS` MARKs
open at once. A batch's STOP starts the next batch's scan afresh: each pickle has its own memo.

The scan also keeps the file's memory ledger. Each opcode is charged, as it is scanned and so
before the unpickler acts on it, at least what the unpickler then allocates for it: the object
it makes (a string at up to 5 bytes a byte of its UTF-8, for a widened copy), a stack and
container slot for what it pushes, a memo slot for what it memoizes (`COSTS`). The unpickler's
own code charges what the names it calls make (`charge`), and what it makes of the loaded batch.
The file's charges together may not pass `memory_budget` of its size: `MEMORY_PER_BYTE` bytes a
byte and `MEMORY_CONSTANT`; so nothing a file holds, a string encoded from the memo a thousand
times or lists nested a million deep, takes more memory than a small multiple of its size. An
argument or frame whose length runs past the end of the file is refused before it is read.

The scan's cost is per opcode: an argument of given length (an array's bytes) is skipped by
count. Only newline-ended arguments, those of protocols 0 and 1, are read byte by byte.

`scan` is the entry point; it checks its buffers first (`engine.buffers.check_buffer`): numba
checks no bounds. Pure numpy/numba: no Ray.
"""

from __future__ import annotations

import pickle
import pickletools

import numpy as np
from numba import njit

from links_ray.engine.buffers import check_buffer

#: The most MARKs a batch may have open at once.
MAX_MARKS = 1000
#: Bytes of memory a file's unpickling may take for each byte of the file, and besides.
MEMORY_PER_BYTE = 64
MEMORY_CONSTANT = 2**20

# What an opcode does to the scan (its _ACTION), and its argument's width or line count (_WIDTH).
_REFUSE, _PLAIN, _MARK, _POP_MARK, _MEMOIZE, _STOP = 0, 1, 2, 3, 4, 5
_FIXED, _SIZED, _LINES, _PUT_LINE, _GET_LINE, _PUT, _GET, _FRAME = 6, 7, 8, 9, 10, 11, 12, 13

#: Each opcode the scan lets through: (what it does, its argument's width or line count).
ALLOWED: dict[bytes, tuple[int, int]] = {
    pickle.PROTO: (_FIXED, 1),
    pickle.FRAME: (_FRAME, 8),
    pickle.STOP: (_STOP, 0),
    pickle.MARK: (_MARK, 0),
    pickle.POP: (_PLAIN, 0),
    pickle.POP_MARK: (_POP_MARK, 0),
    pickle.NONE: (_PLAIN, 0),
    pickle.NEWTRUE: (_PLAIN, 0),
    pickle.NEWFALSE: (_PLAIN, 0),
    pickle.INT: (_LINES, 1),
    pickle.LONG: (_LINES, 1),
    pickle.FLOAT: (_LINES, 1),
    pickle.BININT: (_FIXED, 4),
    pickle.BININT1: (_FIXED, 1),
    pickle.BININT2: (_FIXED, 2),
    pickle.BINFLOAT: (_FIXED, 8),
    pickle.LONG1: (_SIZED, 1),
    pickle.LONG4: (_SIZED, 4),
    pickle.STRING: (_LINES, 1),
    pickle.UNICODE: (_LINES, 1),
    pickle.SHORT_BINSTRING: (_SIZED, 1),
    pickle.BINSTRING: (_SIZED, 4),
    pickle.SHORT_BINUNICODE: (_SIZED, 1),
    pickle.BINUNICODE: (_SIZED, 4),
    pickle.BINUNICODE8: (_SIZED, 8),
    pickle.SHORT_BINBYTES: (_SIZED, 1),
    pickle.BINBYTES: (_SIZED, 4),
    pickle.BINBYTES8: (_SIZED, 8),
    pickle.BYTEARRAY8: (_SIZED, 8),
    pickle.EMPTY_LIST: (_PLAIN, 0),
    pickle.APPEND: (_PLAIN, 0),
    pickle.APPENDS: (_POP_MARK, 0),
    pickle.LIST: (_POP_MARK, 0),
    pickle.EMPTY_TUPLE: (_PLAIN, 0),
    pickle.TUPLE: (_POP_MARK, 0),
    pickle.TUPLE1: (_PLAIN, 0),
    pickle.TUPLE2: (_PLAIN, 0),
    pickle.TUPLE3: (_PLAIN, 0),
    pickle.GLOBAL: (_LINES, 2),
    pickle.STACK_GLOBAL: (_PLAIN, 0),
    pickle.REDUCE: (_PLAIN, 0),
    pickle.BUILD: (_PLAIN, 0),
    pickle.PUT: (_PUT_LINE, 0),
    pickle.BINPUT: (_PUT, 1),
    pickle.LONG_BINPUT: (_PUT, 4),
    pickle.MEMOIZE: (_MEMOIZE, 0),
    pickle.GET: (_GET_LINE, 0),
    pickle.BINGET: (_GET, 1),
    pickle.LONG_BINGET: (_GET, 4),
}
# What the unpickler allocates for an object it pushes beyond the object itself: a slot of its
# stack, grown by an eighth, and one of the list or tuple the object ends in (a list of one item
# has four); and for a memo entry: a slot of the memo table, which doubles.
_PUSHED = 32
_MEMOIZED = 24
#: What each opcode is charged (bytes): a fixed cost and one for each byte of its argument (of
#: its text line for protocol 0's). What a name called by REDUCE or BUILD makes is charged by
#: the unpickler. CPython 3.11's sizes, each rounded up: an int 32, a float 24, bytes 33 and a
#: bytearray 57 before their bytes, a str 80 before its characters, a list 56 and a tuple 40
#: before their slots, each with 16 for the garbage collector.
COSTS: dict[bytes, tuple[int, int]] = {
    **{code: (_PUSHED, 0) for code in (pickle.NONE, pickle.NEWTRUE, pickle.NEWFALSE)},
    **{code: (_PUSHED + 32, 0) for code in (pickle.BININT, pickle.BININT1, pickle.BININT2)},
    pickle.BINFLOAT: (_PUSHED + 24, 0),
    **{code: (_PUSHED + 32, 1) for code in (pickle.INT, pickle.LONG, pickle.FLOAT)},
    **{code: (_PUSHED + 32, 2) for code in (pickle.LONG1, pickle.LONG4)},
    # Python 2 strings: bytes decoded to a str, both held at once.
    **{code: (_PUSHED + 128, 2) for code in (pickle.SHORT_BINSTRING, pickle.BINSTRING)},
    pickle.STRING: (_PUSHED + 128, 2),
    # A str's characters take up to 4 bytes each, and its decoder may widen a copy of them.
    **{
        code: (_PUSHED + 80, 5)
        for code in (pickle.UNICODE, pickle.SHORT_BINUNICODE, pickle.BINUNICODE)
    },
    pickle.BINUNICODE8: (_PUSHED + 80, 5),
    **{code: (_PUSHED + 48, 1) for code in (pickle.SHORT_BINBYTES, pickle.BINBYTES)},
    pickle.BINBYTES8: (_PUSHED + 48, 1),
    pickle.BYTEARRAY8: (_PUSHED + 64, 1),
    **{code: (_PUSHED + 72, 0) for code in (pickle.EMPTY_LIST, pickle.LIST)},
    pickle.EMPTY_TUPLE: (_PUSHED, 0),
    **{
        code: (_PUSHED + 56, 0)
        for code in (pickle.TUPLE, pickle.TUPLE1, pickle.TUPLE2, pickle.TUPLE3)
    },
    # A name's module and name are read as text, then looked up: nothing new is kept.
    pickle.GLOBAL: (_PUSHED, 2),
    pickle.STACK_GLOBAL: (_PUSHED, 0),
    pickle.REDUCE: (_PUSHED, 0),
    **{code: (_PUSHED, 0) for code in (pickle.GET, pickle.BINGET, pickle.LONG_BINGET)},
    **{
        code: (_MEMOIZED, 0)
        for code in (pickle.PUT, pickle.BINPUT, pickle.LONG_BINPUT, pickle.MEMOIZE)
    },
}
_ACTION = np.zeros(256, dtype=np.int64)
_WIDTH = np.zeros(256, dtype=np.int64)
_COST = np.zeros(256, dtype=np.int64)
_PER_BYTE = np.zeros(256, dtype=np.int64)
for _code, (_action, _width) in ALLOWED.items():
    _ACTION[_code[0]] = _action
    _WIDTH[_code[0]] = _width
for _code, (_cost, _per_byte) in COSTS.items():
    _COST[_code[0]] = _cost
    _PER_BYTE[_code[0]] = _per_byte

#: Why the scan stopped (state[REASON]).
REFUSED_OPCODE, PUT_OUT_OF_ORDER, GET_NOT_PUT, TOO_MANY_MARKS, NOT_AN_INDEX = 1, 2, 3, 4, 5
OVER_BUDGET, PAST_END = 6, 7
# The scan's state, carried from chunk to chunk: what it is reading (_MODE), how much of it is
# left (_COUNT), the integer read so far (_VALUE) and its shift or digit count (_SHIFT), the
# opcode it belongs to and where that began, the batch's memo entries and open MARKs, the bytes
# scanned, the refusal (why, its opcode and where), the stream's length (END), the bytes its
# objects are charged (SPENT) and the most they may be (BUDGET).
(
    _MODE,
    _COUNT,
    _VALUE,
    _SHIFT,
    _OPCODE,
    _OPCODE_AT,
    _MEMO,
    _MARKS,
    _POSITION,
    REASON,
    REFUSED,
    REFUSED_AT,
    END,
    SPENT,
    BUDGET,
) = range(15)
STATE_SIZE = 15
_EXPECT_OPCODE, _SKIP, _LITTLE_ENDIAN, _TO_NEWLINE, _DECIMAL = 0, 1, 2, 3, 4


#: The length and budget of a stream whose length is not given.
_UNBOUNDED = 1 << 62


def memory_budget(size: int) -> int:
    """The most bytes the objects unpickled from a file of `size` bytes may take."""
    return MEMORY_PER_BYTE * size + MEMORY_CONSTANT


def new_state(size: int | None = None) -> np.ndarray:
    """The scan's state at the start of a file of `size` bytes (unbounded if None): expecting
    an opcode, nothing refused, nothing charged against the file's `memory_budget`."""
    state = np.zeros(STATE_SIZE, dtype=np.int64)
    state[END] = _UNBOUNDED if size is None else size
    state[BUDGET] = _UNBOUNDED if size is None else memory_budget(size)
    return state


def charge(state: np.ndarray, size: int) -> None:
    """Charge `size` bytes more to the file whose scan `state` holds; UnpicklingError if its
    objects then take more than its budget."""
    spent = int(state[SPENT]) + size
    state[SPENT] = spent
    if spent > state[BUDGET]:
        raise pickle.UnpicklingError(f"its objects would take more than {_budget(state)}")


def _budget(state: np.ndarray) -> str:
    return (
        f"{int(state[BUDGET]):,} bytes of memory, the budget of a file of "
        f"{int(state[END]):,} bytes ({MEMORY_PER_BYTE} a byte and {MEMORY_CONSTANT:,})"
    )


@njit(cache=True, nogil=True)
def _refuse(state: np.ndarray, reason: int) -> None:
    state[REASON] = reason
    state[REFUSED] = state[_OPCODE]
    state[REFUSED_AT] = state[_OPCODE_AT]


@njit(cache=True, nogil=True)
def _scan(
    chunk: np.ndarray,
    state: np.ndarray,
    action: np.ndarray,
    width: np.ndarray,
    cost: np.ndarray,
    per_byte: np.ndarray,
) -> int:
    """Scan `chunk`, the bytes after state[_POSITION]; return how many of them may be handed
    on: all, or those before the opcode refused (its reason in state[REASON])."""
    start = state[_POSITION]
    size = chunk.shape[0]
    if state[REASON] != 0:
        return 0
    i = 0
    while i < size:
        mode = state[_MODE]
        if mode == _EXPECT_OPCODE:
            code = np.int64(chunk[i])
            state[_OPCODE] = code
            state[_OPCODE_AT] = start + i
            i += 1
            what = action[code]
            if what == _REFUSE:
                _refuse(state, REFUSED_OPCODE)
                break
            state[SPENT] += cost[code]
            if state[SPENT] > state[BUDGET]:
                _refuse(state, OVER_BUDGET)
                break
            if what == _PLAIN:
                continue
            if what == _MARK:
                if state[_MARKS] >= MAX_MARKS:
                    _refuse(state, TOO_MANY_MARKS)
                    break
                state[_MARKS] += 1
            elif what == _POP_MARK:
                # A pop with no MARK open is the unpickler's to refuse.
                if state[_MARKS] > 0:
                    state[_MARKS] -= 1
            elif what == _MEMOIZE:
                state[_MEMO] += 1
            elif what == _STOP:
                state[_MEMO] = 0
                state[_MARKS] = 0
            elif what == _FIXED:
                state[_MODE] = _SKIP
                state[_COUNT] = width[code]
            elif what == _SIZED or what == _PUT or what == _GET or what == _FRAME:
                state[_MODE] = _LITTLE_ENDIAN
                state[_COUNT] = width[code]
                state[_VALUE] = 0
                state[_SHIFT] = 0
            elif what == _LINES:
                state[_MODE] = _TO_NEWLINE
                state[_COUNT] = width[code]
            else:  # a PUT or GET with a decimal index
                state[_MODE] = _DECIMAL
                state[_VALUE] = 0
                state[_SHIFT] = 0
        elif mode == _SKIP:
            step = min(state[_COUNT], size - i)
            i += step
            state[_COUNT] -= step
            if state[_COUNT] == 0:
                state[_MODE] = _EXPECT_OPCODE
        elif mode == _LITTLE_ENDIAN:
            state[_VALUE] |= np.int64(chunk[i]) << state[_SHIFT]
            state[_SHIFT] += 8
            state[_COUNT] -= 1
            i += 1
            if state[_COUNT] > 0:
                continue
            value = state[_VALUE]
            what = action[state[_OPCODE]]
            state[_MODE] = _EXPECT_OPCODE
            if what == _SIZED or what == _FRAME:
                # A length read as negative is past int64, and past any file's end.
                if value < 0 or value > state[END] - (start + i):
                    _refuse(state, PAST_END)
                    break
                if what == _SIZED and value != 0:
                    state[SPENT] += per_byte[state[_OPCODE]] * value
                    if state[SPENT] > state[BUDGET]:
                        _refuse(state, OVER_BUDGET)
                        break
                    state[_MODE] = _SKIP
                    state[_COUNT] = value
            elif what == _PUT:
                if value != state[_MEMO]:
                    _refuse(state, PUT_OUT_OF_ORDER)
                    break
                state[_MEMO] += 1
            elif value >= state[_MEMO]:
                _refuse(state, GET_NOT_PUT)
                break
        elif mode == _TO_NEWLINE:
            state[SPENT] += per_byte[state[_OPCODE]]
            if state[SPENT] > state[BUDGET]:
                _refuse(state, OVER_BUDGET)
                break
            if chunk[i] == 10:
                state[_COUNT] -= 1
                if state[_COUNT] == 0:
                    state[_MODE] = _EXPECT_OPCODE
            i += 1
        else:
            byte = np.int64(chunk[i])
            i += 1
            put = action[state[_OPCODE]] == _PUT_LINE
            if byte == 10:
                if state[_SHIFT] == 0:
                    _refuse(state, NOT_AN_INDEX)
                    break
                state[_MODE] = _EXPECT_OPCODE
                if put:
                    if state[_VALUE] != state[_MEMO]:
                        _refuse(state, PUT_OUT_OF_ORDER)
                        break
                    state[_MEMO] += 1
                continue
            if byte < 48 or byte > 57:
                _refuse(state, NOT_AN_INDEX)
                break
            state[_VALUE] = state[_VALUE] * 10 + (byte - 48)
            state[_SHIFT] += 1
            # Refused at the digit that overshoots: what was handed on never names an index
            # past the memo, and the value never overflows.
            if put and state[_VALUE] > state[_MEMO]:
                _refuse(state, PUT_OUT_OF_ORDER)
                break
            if not put and state[_VALUE] >= state[_MEMO]:
                _refuse(state, GET_NOT_PUT)
                break
    if state[REASON] != 0:
        # The refused opcode may have begun in an earlier chunk, already handed on.
        accepted = max(state[REFUSED_AT] - start, 0)
        state[_POSITION] = start + accepted
        return accepted
    state[_POSITION] = start + size
    return size


def scan(chunk: np.ndarray, state: np.ndarray) -> int:
    """Scan `chunk` (uint8), the next bytes of the stream whose scan `state` (from
    `new_state`) holds; return how many of them may be handed to the unpickler. Fewer than
    all once an opcode is refused: `refusal(state)` then says which and why, and every later
    chunk is refused whole."""
    check_buffer("chunk", chunk, (None,), np.uint8)
    check_buffer("state", state, (STATE_SIZE,), np.int64, contiguous=True, writeable=True)
    return _scan(chunk, state, _ACTION, _WIDTH, _COST, _PER_BYTE)


#: Opcodes' names by byte, as pickletools gives them.
_NAMES = {ord(opcode.code): opcode.name for opcode in pickletools.opcodes}
_DICTS_AND_SETS = frozenset(
    code[0]
    for code in (
        pickle.EMPTY_DICT,
        pickle.DICT,
        pickle.SETITEM,
        pickle.SETITEMS,
        pickle.EMPTY_SET,
        pickle.ADDITEMS,
        pickle.FROZENSET,
    )
)
_BUFFERS = frozenset((pickle.NEXT_BUFFER[0], pickle.READONLY_BUFFER[0]))


def refusal(state: np.ndarray) -> str | None:
    """Why the scan of `state` stopped, in one line naming the opcode and its byte offset
    in the stream, or None if it has not."""
    reason = int(state[REASON])
    if reason == 0:
        return None
    code = int(state[REFUSED])
    name = _NAMES.get(code)
    opcode = f"{name} ({bytes([code])!r})" if name else f"byte {code:#04x}"
    at = f"at byte {int(state[REFUSED_AT])}"
    if reason == REFUSED_OPCODE:
        if name is None:
            return f"{opcode} {at} is no pickle opcode"
        if code in _DICTS_AND_SETS:
            why = "the release's batches hold no dict or set"
        elif code in _BUFFERS:
            why = "out-of-band buffers are not read"
        else:
            why = "a pickle of lists of numpy arrays never holds it"
        return f"opcode {opcode} {at} is not read: {why}"
    return (
        f"opcode {opcode} {at} "
        + {
            PUT_OUT_OF_ORDER: f"puts a memo index other than the next, {int(state[_MEMO])}",
            GET_NOT_PUT: f"gets a memo index not put (the batch has put {int(state[_MEMO])})",
            TOO_MANY_MARKS: f"opens more than {MAX_MARKS} MARKs at once",
            NOT_AN_INDEX: "gives a memo index that is not a decimal number",
            OVER_BUDGET: f"would take the file's objects past {_budget(state)}",
            PAST_END: f"gives a length past the end of the file, byte {int(state[END]):,}",
        }[reason]
    )
