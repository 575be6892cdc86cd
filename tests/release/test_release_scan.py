"""The opcode filter's kernel on its own: it lets every real release batch through whole (every
protocol, with and without a memo, numpy 1's names), refuses each opcode outside `ALLOWED` by
name, memo indices out of order and too many MARKs, and gives the same verdict for a stream fed
in chunks of any size as fed whole (an opcode, a length or a memo index split between reads)."""

from __future__ import annotations

import io
import pickle
import pickletools

import numpy as np
import pytest

from links_ray.release.opcode_scan import (
    ALLOWED,
    MAX_MARKS,
    memory_budget,
    new_state,
    refusal,
    scan,
)
from tests.release.test_release_pickles import real_values
from tests.support.fuzz_release_pickles import make_seeds


def scanned(data: bytes, chunk: int | None = None) -> tuple[int, str | None]:
    """(bytes handed on, refusal) of scanning `data` in chunks of `chunk` bytes (all at once
    if None)."""
    state = new_state()
    handed = 0
    step = chunk or max(len(data), 1)
    for start in range(0, len(data), step):
        piece = np.frombuffer(data[start : start + step], np.uint8)
        handed += scan(piece, state)
    return handed, refusal(state)


def real_streams() -> dict[str, bytes]:
    """Release-shaped files of every protocol (the fuzzer's seeds) and every array and scalar
    kind, pickled with and without a memo."""
    streams = {seed.name: seed.data for seed in make_seeds()}
    for protocol in range(6):
        for memo in (True, False):
            written = io.BytesIO()
            # A pickler per batch, as pickle.dump makes: each batch's memo starts afresh.
            for batch in (real_values(), real_values()[:3]):
                pickler = pickle.Pickler(written, protocol=protocol)
                pickler.fast = not memo
                pickler.dump(batch)
            streams[f"kinds p{protocol}{'' if memo else ' no memo'}"] = written.getvalue()
    return streams


def test_real_release_batches_pass_whole() -> None:
    for name, data in real_streams().items():
        assert scanned(data) == (len(data), None), name


def test_the_allowed_opcodes_are_those_real_batches_and_plain_values_use() -> None:
    used = set()
    for data in real_streams().values():
        stream = io.BytesIO(data)
        while stream.tell() < len(data):
            used.update(opcode.name for opcode, _, _ in pickletools.genops(stream))
    allowed = {
        opcode.name for opcode in pickletools.opcodes if opcode.code.encode("latin1") in ALLOWED
    }
    assert used <= allowed
    # What plain ints, strings, bytes and tuples need beyond the batches' own.
    plain = {
        "BININT2",
        "LONG",
        "LONG1",
        "LONG4",
        "STRING",
        "BINSTRING",
        "SHORT_BINSTRING",
        "BINUNICODE8",
        "BINBYTES8",
        "LONG_BINGET",
        "POP",
        "POP_MARK",
    }
    assert allowed - used == plain


@pytest.mark.parametrize(
    "opcode", [op for op in pickletools.opcodes if op.code.encode("latin1") not in ALLOWED]
)
def test_each_refused_opcode_is_named_where_it_is(opcode: pickletools.OpcodeInfo) -> None:
    data = b"\x80\x04K\x01" + opcode.code.encode("latin1") + b"\x00" * 16 + b"."
    handed, why = scanned(data)
    assert handed == 4
    assert why is not None and why.startswith(f"opcode {opcode.name} (") and " at byte 4 " in why


def test_a_byte_that_is_no_opcode_is_refused() -> None:
    assert scanned(b"\x80\x04\xff.") == (2, "byte 0xff at byte 2 is no pickle opcode")


MEMO_REFUSALS = {
    # LONG_BINPUT near 2**30: the unpickler would size its memo table for it.
    "huge LONG_BINPUT": (b"\x80\x02]r\x00\x00\x00\x40.", 3, "LONG_BINPUT", "other than the next"),
    "huge PUT": (b"(lp1073741824\n.", 2, "PUT", "other than the next"),
    "PUT skipping one": (b"\x80\x02]q\x01.", 3, "BINPUT", "other than the next, 0"),
    "PUT again": (b"\x80\x04]\x94]q\x00.", 5, "BINPUT", "other than the next, 1"),
    "GET not put": (b"\x80\x02]q\x00h\x01.", 5, "BINGET", "not put (the batch has put 1)"),
    "LONG_BINGET not put": (b"\x80\x02]j\x00\x00\x01\x00.", 3, "LONG_BINGET", "not put"),
    "GET protocol 0": (b"(lp0\ng10\n.", 5, "GET", "not put"),
    "PUT not decimal": (b"(lp+0\n.", 2, "PUT", "not a decimal number"),
    "PUT empty": (b"(lp\n.", 2, "PUT", "not a decimal number"),
    "memo of an earlier batch": (b"\x80\x04]\x94.\x80\x04h\x00.", 7, "BINGET", "not put"),
}


@pytest.mark.parametrize("case", MEMO_REFUSALS, ids=list(MEMO_REFUSALS))
def test_memo_indices_out_of_order_are_refused(case: str) -> None:
    data, at, name, why = MEMO_REFUSALS[case]
    handed, refused = scanned(data)
    assert handed == at
    assert refused is not None and refused.startswith(f"opcode {name} (")
    assert f" at byte {at} " in refused and why in refused


def test_marks_are_bounded() -> None:
    deep = b"\x80\x04" + b"(" * MAX_MARKS + b"t" * MAX_MARKS + b"."
    assert scanned(deep) == (len(deep), None)
    deeper = b"\x80\x04" + b"(" * (MAX_MARKS + 1)
    handed, refused = scanned(deeper)
    assert handed == 2 + MAX_MARKS and "more than 1000 MARKs" in str(refused)


def refused_streams() -> dict[str, bytes]:
    """Real batches with a refusal after them: in the next batch, inside a frame, after a
    split length or a protocol 0 line."""
    values = real_values()
    p4 = pickle.dumps(values, 4)
    p0 = pickle.dumps(values[:4], 0)
    return {
        "dict after a batch": p4 + b"\x80\x04}.",
        "dict in a frame": p4[:-1] + b"}.",
        "set after bytes": pickle.dumps([b"x" * 300], 4)[:-1] + b"\x8f.",
        "PUT after protocol 0 lines": p0[:-1] + b"p1073741824\n.",
        "GET after BINBYTES8": b"\x80\x04\x8e\x05" + bytes(7) + b"abcde" + b"h\x07.",
        "out of order LONG_BINPUT": p4[:-1] + b"r\x00\x00\x00\x40.",
        **{name: data for name, (data, *_) in MEMO_REFUSALS.items()},
    }


def test_chunks_of_every_size_give_the_verdict_of_the_whole() -> None:
    streams = {**refused_streams(), "kinds p0": pickle.dumps(real_values()[:6], 0)}
    streams["kinds p5"] = pickle.dumps(real_values(), 5)
    for name, data in streams.items():
        whole, why = scanned(data)
        sizes = range(1, min(len(data), 600) + 1)
        for size in [*sizes, len(data) // 3, len(data) // 2 + 1]:
            handed, refused = scanned(data, size)
            assert refused == why, (name, size)
            if handed != whole:
                # A memo index is refused when read whole (a decimal one at the digit that
                # decides): the part of its opcode in earlier chunks was handed on, never all
                # of it, so the unpickler runs out before it acts on it.
                opcode = data[whole : whole + 1]
                assert handed > whole, (name, size)
                if opcode in (b"p", b"g"):
                    assert b"\n" not in data[whole:handed], (name, size)
                else:
                    width = {b"q": 1, b"h": 1, b"r": 4, b"j": 4}[opcode]
                    assert handed - whole <= width, (name, size)


def test_every_later_chunk_is_refused_whole() -> None:
    state = new_state()
    assert scan(np.frombuffer(b"\x80\x04K\x01}", np.uint8), state) == 4
    assert scan(np.frombuffer(b"\x80\x04.", np.uint8), state) == 0


def test_scan_checks_its_buffers() -> None:
    with pytest.raises(ValueError, match="chunk"):
        scan(np.zeros(4, np.int64), new_state())
    with pytest.raises(ValueError, match="state"):
        scan(np.zeros(4, np.uint8), np.zeros(3, np.int64))


def test_the_budget_and_the_files_end_give_the_same_verdict_in_any_chunks() -> None:
    # 100,000 EMPTY_LISTs, each charged a list and its slot (104 bytes): the budget of a
    # 100 KB file (7.4 MB) runs out at the same opcode however the file is read.
    lists = b"\x80\x02(" + b"]" * 100_000
    # A length is refused before all of it is handed on: the unpickler never allocates it.
    past_end = b"\x80\x04\x8e" + (100).to_bytes(8, "little") + bytes(50)
    past_frame = b"\x80\x04\x95" + (100).to_bytes(8, "little") + b"N."
    for data, why, most in (
        (lists, "would take the file's objects past", memory_budget(len(lists)) // 64),
        (past_end, "opcode BINBYTES8 (b'\\x8e') at byte 2 gives a length past the end", 10),
        (past_frame, "opcode FRAME (b'\\x95') at byte 2 gives a length past the end", 10),
    ):
        refusals = set()
        for chunk in (1, 7, 4096, len(data)):
            state = new_state(len(data))
            handed = 0
            for start in range(0, len(data), chunk):
                handed += scan(np.frombuffer(data[start : start + chunk], np.uint8), state)
            refusals.add(refusal(state))
            assert handed <= most, (chunk, handed)
        assert len(refusals) == 1, refusals
        (refused,) = refusals
        assert refused is not None and why in refused, refused
