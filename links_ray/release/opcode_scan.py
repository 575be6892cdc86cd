"""The opcode filter in front of the release unpickler: a scan of a pickle's opcode stream, chunk
by chunk, that stops at the first opcode a release file never holds.

CPython's C unpickler acts on some opcodes before any code of ours sees their result: SETITEM
and ADDITEMS hash their keys (a tuple's hash recurses with no depth check), and PUT sizes the
memo table by the index the file gives. The release's batches are lists of numpy arrays and
scalars written by `pickle.dump`, so the scan allows only the opcodes such pickles and plain
lists, tuples, numbers, strings and bytes use (`ALLOWED`), memo indices in the order the pickler
writes them (each PUT the next index, each GET one already put), and at most `MAX_MARKS` MARKs
open at once. A batch's STOP starts the next batch's scan afresh: each pickle has its own memo.

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

# What an opcode does to the scan (its _ACTION), and its argument's width or line count (_WIDTH).
_REFUSE, _PLAIN, _MARK, _POP_MARK, _MEMOIZE, _STOP = 0, 1, 2, 3, 4, 5
_FIXED, _SIZED, _LINES, _PUT_LINE, _GET_LINE, _PUT, _GET = 6, 7, 8, 9, 10, 11, 12

#: Each opcode the scan lets through: (what it does, its argument's width or line count).
ALLOWED: dict[bytes, tuple[int, int]] = {
    pickle.PROTO: (_FIXED, 1),
    pickle.FRAME: (_FIXED, 8),
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
_ACTION = np.zeros(256, dtype=np.int64)
_WIDTH = np.zeros(256, dtype=np.int64)
for _code, (_action, _width) in ALLOWED.items():
    _ACTION[_code[0]] = _action
    _WIDTH[_code[0]] = _width

#: Why the scan stopped (state[REASON]).
REFUSED_OPCODE, PUT_OUT_OF_ORDER, GET_NOT_PUT, TOO_MANY_MARKS, NOT_AN_INDEX = 1, 2, 3, 4, 5
# The scan's state, carried from chunk to chunk: what it is reading (_MODE), how much of it is
# left (_COUNT), the integer read so far (_VALUE) and its shift or digit count (_SHIFT), the
# opcode it belongs to and where that began, the batch's memo entries and open MARKs, the bytes
# scanned, and the refusal (why, its opcode and where).
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
) = range(12)
STATE_SIZE = 12
_EXPECT_OPCODE, _SKIP, _LITTLE_ENDIAN, _TO_NEWLINE, _DECIMAL = 0, 1, 2, 3, 4
#: An 8-byte length past int64 (the unpickler refuses it): skipped as this many bytes.
_ENDLESS = 1 << 62


def new_state() -> np.ndarray:
    """The scan's state at the start of a file: expecting an opcode, nothing refused."""
    return np.zeros(STATE_SIZE, dtype=np.int64)


@njit(cache=True, nogil=True)
def _refuse(state: np.ndarray, reason: int) -> None:
    state[REASON] = reason
    state[REFUSED] = state[_OPCODE]
    state[REFUSED_AT] = state[_OPCODE_AT]


@njit(cache=True, nogil=True)
def _scan(chunk: np.ndarray, state: np.ndarray, action: np.ndarray, width: np.ndarray) -> int:
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
            if what == _PLAIN:
                continue
            if what == _REFUSE:
                _refuse(state, REFUSED_OPCODE)
                break
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
            elif what == _SIZED or what == _PUT or what == _GET:
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
            if what == _SIZED:
                if value != 0:
                    state[_MODE] = _SKIP
                    state[_COUNT] = value if value > 0 else _ENDLESS
            elif what == _PUT:
                if value != state[_MEMO]:
                    _refuse(state, PUT_OUT_OF_ORDER)
                    break
                state[_MEMO] += 1
            elif value >= state[_MEMO]:
                _refuse(state, GET_NOT_PUT)
                break
        elif mode == _TO_NEWLINE:
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
    return _scan(chunk, state, _ACTION, _WIDTH)


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
        }[reason]
    )
