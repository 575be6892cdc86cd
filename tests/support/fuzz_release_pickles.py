"""Fuzzing the release unpickler: release batches, mutated, read as `links import-release`
reads them.

Seed files are release batches as the release and links-ray's export pickle them: the
dataset's `[A, x0, node_type]`, the simulations' `[x_sol, j]` and the curated `[curve, j,
node]`, plus a batch of every array and scalar kind a release file may hold, written by
`pickle.dumps` with protocols 0 to 5 (numpy 1's module names too) and, as the export writes
them, by a protocol 4 pickler without a memo; a file is one to three batches. Each case mutates
one seed (bits, bytes, truncation, opcodes deleted, repeated, swapped or brought in from another
seed, integer arguments set to edge values, pieces of another seed spliced in) and reads every
batch of it with `links_ray.release.pickles.read_pickles`.

The property: a case either loads, holding only lists, tuples, plain values and numpy arrays
and scalars of the release's plain dtypes (`links_ray.bench.pickle_fuzz.not_plain`; the
seed's own batches, or others when the mutation changed data), or is refused with a one-line
ReleaseFileError. The grammar fuzzer builds pickles opcode by opcode instead
(`links_ray.bench.pickle_grammar`) and measures each file's memory against its budget
(`links_ray.bench.pickle_fuzz`). Any other exception is a violation; a signal ends the
run, which its caller sees in the exit status. The run prints its counts as one JSON object and
exits 1 if there was a violation.

Run from the repository root (cases are numbered and each is reproducible on its own):

    python -m tests.support.fuzz_release_pickles --cases 100000
    python -m tests.support.fuzz_release_pickles --case 1234  # one case: its mutation and outcome
"""

from __future__ import annotations

import argparse
import io
import json
import pickle
import pickletools
import resource
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from links_ray.bench.pickle_fuzz import not_plain
from links_ray.release.pickles import ReleaseFileError, read_pickles

#: Integer arguments written into opcodes: edges of sizes, signs and widths.
EDGE_INTEGERS = (0, 1, 2, 3, 7, 8, 255, 256, 2**15, 2**16 - 1, 2**27, 2**31 - 1, 2**31, 2**32 - 1)
#: The width of an opcode's integer argument, or of its argument's length, by pickletools' n.
ARGUMENT_WIDTHS = {
    1: 1,
    2: 2,
    4: 4,
    8: 8,
    pickletools.TAKEN_FROM_ARGUMENT1: 1,
    pickletools.TAKEN_FROM_ARGUMENT4: 4,
    pickletools.TAKEN_FROM_ARGUMENT4U: 4,
    pickletools.TAKEN_FROM_ARGUMENT8U: 8,
}
#: How many worst cases of each kind a report keeps.
KEPT = 20


@dataclass(frozen=True)
class Seed:
    """A seed file: its bytes, its batches as pickle.loads reads them, its opcodes' spans."""

    name: str
    data: bytes
    batches: list[Any]
    opcodes: list[tuple[int, int, str, int]]  # (start, end, opcode name, argument width)


def release_batches(rng: np.random.Generator) -> dict[str, list]:
    """One batch of each release file, small: the dataset, its simulations, curated curves."""
    dataset, simulations, curated = [], [], []
    for j in range(int(rng.integers(2, 5))):
        n = int(rng.integers(4, 8))
        upper = np.triu(rng.random((n, n)) < 0.4, 1)
        fixed = np.zeros(n, dtype=bool)
        fixed[[0, 2]] = True
        dataset.append([upper | upper.T, rng.random((n, 2), dtype=np.float32), fixed])
        if j % 2 == 0:
            simulations.append([rng.random((n, 200, 2), dtype=np.float32), j])
            curated.append([rng.random((200, 2), dtype=np.float32), j, int(rng.integers(n))])
    return {"dataset": dataset, "simulations": simulations, "curated": curated}


def kinds_batch(rng: np.random.Generator) -> list:
    """A batch of every array and scalar kind a release file may hold, in both orders."""
    square = rng.random((3, 4))
    return [
        [square.astype(np.float32), np.asfortranarray(square), square.astype(">f8")],
        [np.arange(6, dtype=np.int64), np.arange(4, dtype=">i4"), np.arange(3, dtype=np.uint16)],
        [np.array([b"ab", b"c"]), np.array(True), np.zeros((0, 2)), np.zeros(0, dtype="S3")],
        (np.int64(7), np.float32(1.5), np.bool_(False), np.bytes_(b"xy"), np.uint8(3)),
        [1, 2.5, "text", b"raw", None, True],
    ]


def pickled(batch: Any, protocol: int, memo: bool = True) -> bytes:
    """`batch` as pickle.dump writes it, or as the export does (no memo) if not `memo`."""
    out = io.BytesIO()
    pickler = pickle.Pickler(out, protocol=protocol)
    pickler.fast = not memo
    pickler.dump(batch)
    return out.getvalue()


def opcode_spans(data: bytes) -> list[tuple[int, int, str, int]]:
    """(start, end, name, argument width) of each opcode of the pickles in `data`."""
    spans = []
    start = 0
    while start < len(data):
        batch = io.BytesIO(data[start:])
        ops = list(pickletools.genops(batch))
        for (op, _, pos), following in zip(ops, [*ops[1:], None], strict=True):
            end = following[2] if following else pos + 1
            width = 0 if op.arg is None else ARGUMENT_WIDTHS.get(op.arg.n, 0)
            spans.append((start + pos, start + end, op.name, width))
        start += batch.tell()
    return spans


def make_seeds() -> list[Seed]:
    """The seed files, the same on every run."""
    rng = np.random.default_rng(20261126)
    files = release_batches(rng)
    kinds = kinds_batch(rng)
    seeds = []
    for protocol in range(6):
        for name, batch in [*files.items(), ("kinds", kinds)]:
            seeds.append((f"{name} p{protocol}", [batch], protocol, True))
        seeds.append((f"dataset+simulations p{protocol}", list(files.values())[:2], protocol, True))
    for name, batch in files.items():
        seeds.append((f"{name} p4 no memo (the export's)", [batch], 4, False))
    seeds.append(("all files p4 no memo", [*files.values(), kinds], 4, False))
    made = []
    for name, batches, protocol, memo in seeds:
        data = b"".join(pickled(batch, protocol, memo) for batch in batches)
        made.append(Seed(name, data, batches, opcode_spans(data)))
        if protocol <= 2:  # GLOBAL names are text lines: numpy 1's names are a replacement
            numpy1 = data.replace(b"numpy._core.", b"numpy.core.")
            made.append(Seed(f"{name} numpy 1", numpy1, batches, opcode_spans(numpy1)))
    return made


def mutated(seed: Seed, seeds: list[Seed], rng: np.random.Generator) -> tuple[bytes, str]:
    """`seed`'s bytes changed by one to three mutations, and what they were."""
    data = bytearray(seed.data)
    spans = seed.opcodes
    done = []
    for _ in range(int(rng.choice([1, 1, 1, 2, 3]))):
        mutation = MUTATIONS[int(rng.integers(len(MUTATIONS)))]
        done.append(mutation(data, spans, seeds, rng))
        spans = [] if len(data) != len(seed.data) else spans  # spans hold while sizes do
    return bytes(data), "; ".join(done)


def _position(data: bytearray, spans: list, rng: np.random.Generator) -> int:
    # Half the positions fall on opcodes and their arguments, not on arrays' bytes.
    if spans and rng.random() < 0.5:
        start, end, _, _ = spans[int(rng.integers(len(spans)))]
        return int(rng.integers(start, end))
    return int(rng.integers(max(len(data), 1)))


def flip_bits(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    where = []
    for _ in range(int(rng.integers(1, 5))):
        at = _position(data, spans, rng)
        if at < len(data):
            data[at] ^= 1 << int(rng.integers(8))
            where.append(at)
    return f"bits flipped at {where}"


def set_bytes(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    where = []
    for _ in range(int(rng.integers(1, 5))):
        at = _position(data, spans, rng)
        if at < len(data):
            data[at] = int(rng.choice([0, 0xFF, 0x7F, 0x80, int(rng.integers(256))]))
            where.append(at)
    return f"bytes set at {where}"


def insert_bytes(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    at = _position(data, spans, rng)
    data[at:at] = rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8).tobytes()
    return f"bytes inserted at {at}"


def delete_bytes(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    at = _position(data, spans, rng)
    count = int(rng.integers(1, 17))
    del data[at : at + count]
    return f"{count} bytes deleted at {at}"


def truncate(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    at = _position(data, spans, rng)
    del data[at:]
    return f"cut at {at}"


def _opcode(spans: list, rng: np.random.Generator) -> tuple[int, int, str, int] | None:
    return spans[int(rng.integers(len(spans)))] if spans else None


def delete_opcode(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    found = _opcode(spans, rng)
    if found is None:
        return truncate(data, spans, seeds, rng)
    start, end, name, _ = found
    del data[start:end]
    return f"{name} deleted at {start}"


def repeat_opcode(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    found = _opcode(spans, rng)
    if found is None:
        return insert_bytes(data, spans, seeds, rng)
    start, end, name, _ = found
    data[end:end] = data[start:end]
    return f"{name} at {start} repeated"


def swap_opcodes(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    if len(spans) < 2:
        return flip_bits(data, spans, seeds, rng)
    first, second = sorted(int(i) for i in rng.choice(len(spans), 2, replace=False))
    (a, b, name_a, _), (c, d, name_b, _) = spans[first], spans[second]
    data[a:d] = data[c:d] + data[b:c] + data[a:b]
    return f"{name_a} at {a} swapped with {name_b} at {c}"


def bring_opcode(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    other = seeds[int(rng.integers(len(seeds)))]
    start, end, name, _ = other.opcodes[int(rng.integers(len(other.opcodes)))]
    at = _position(data, spans, rng)
    data[at:at] = other.data[start:end]
    return f"{name} of {other.name} inserted at {at}"


def edge_argument(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    numbered = [span for span in spans if span[3]]
    if not numbered:
        return set_bytes(data, spans, seeds, rng)
    start, _, name, width = numbered[int(rng.integers(len(numbered)))]
    value = int(rng.choice(EDGE_INTEGERS)) % (1 << (8 * width))
    if rng.random() < 0.2:
        value = (1 << (8 * width)) - 1 - value  # negative, read as signed
    data[start + 1 : start + 1 + width] = value.to_bytes(width, "little")
    return f"{name} at {start} given {value}"


def splice(data: bytearray, spans: list, seeds: list[Seed], rng: np.random.Generator) -> str:
    other = seeds[int(rng.integers(len(seeds)))]
    begin = int(rng.integers(len(other.data)))
    piece = other.data[begin : begin + int(rng.integers(1, 400))]
    at = _position(data, spans, rng)
    replaced = int(rng.integers(0, 2 * len(piece) + 1))
    data[at : at + replaced] = piece
    return f"{len(piece)} bytes of {other.name} at {begin} spliced over {replaced} at {at}"


MUTATIONS: list[Callable[[bytearray, list, list[Seed], np.random.Generator], str]] = [
    flip_bits,
    set_bytes,
    insert_bytes,
    delete_bytes,
    truncate,
    delete_opcode,
    repeat_opcode,
    swap_opcodes,
    bring_opcode,
    edge_argument,
    splice,
]


def same(loaded: Any, original: Any) -> bool:
    """Whether `loaded` is `original`'s batches: the same structure, types, dtypes, shapes,
    memory order and bytes."""
    waiting = [(loaded, original)]
    while waiting:
        got, want = waiting.pop()
        if type(got) is not type(want):
            return False
        if type(want) in (list, tuple):
            if len(got) != len(want):
                return False
            waiting.extend(zip(got, want, strict=True))
        elif isinstance(want, np.ndarray | np.generic):
            if got.dtype != want.dtype or got.shape != want.shape:
                return False
            if isinstance(want, np.ndarray) and (
                got.flags.f_contiguous != want.flags.f_contiguous
                or got.tobytes("A") != want.tobytes("A")
            ):
                return False
            if isinstance(want, np.generic) and got.tobytes() != want.tobytes():
                return False
        elif got != want:
            return False
    return True


def outcome(data: bytes, seed: Seed) -> tuple[str, str]:
    """(kind, detail) of reading `data`: loaded_same, loaded_different, refused_name,
    refused_cut_short, refused_content, or violation."""
    try:
        batches = [value for _, _, value in read_pickles(io.BytesIO(data), "fuzz", len(data))]
    except ReleaseFileError as exc:
        message = str(exc)
        if "\n" in message:
            return "violation", f"a ReleaseFileError of several lines: {message[:300]!r}"
        if " names " in message:
            return "refused_name", message.split(" names ", 1)[1].split(";")[0]
        if "is cut short" in message:
            return "refused_cut_short", ""
        return "refused_content", _reason_kind(message.split("pickle: ", 1)[-1])
    except BaseException as exc:  # any other exception is what is looked for
        return "violation", f"{type(exc).__name__}: {str(exc)[:300]}"
    wrong = not_plain(batches)
    if wrong is not None:
        return "violation", f"loaded {wrong}"
    if len(batches) == len(seed.batches) and same(batches, seed.batches):
        return "loaded_same", ""
    return "loaded_different", ""


def _reason_kind(reason: str) -> str:
    # The reason's words without its numbers and names, so that like reasons count together.
    words = [w for w in reason.split()[:8] if not any(c.isdigit() for c in w)]
    return " ".join(words)[:80]


def limit_address_space(extra_mib: int) -> None:
    """Let this process map at most `extra_mib` MiB more than it has now: a crafted allocation
    is then a MemoryError, not a machine swapping."""
    status = Path("/proc/self/status").read_text()
    mapped = int(status.split("VmSize:")[1].split()[0]) * 1024
    resource.setrlimit(resource.RLIMIT_AS, (mapped + extra_mib * 2**20, resource.RLIM_INFINITY))


def run(cases: int, seed: int, first: int = 0) -> dict[str, Any]:
    """Cases `first` to `first + cases - 1` of run `seed`; the counts."""
    seeds = make_seeds()
    counts: Counter[str] = Counter()
    reasons: Counter[str] = Counter()
    mutations: Counter[str] = Counter()
    violations: list[dict] = []
    started = time.perf_counter()
    for case in range(first, first + cases):
        rng = np.random.default_rng([seed, case])
        chosen = seeds[int(rng.integers(len(seeds)))]
        data, how = mutated(chosen, seeds, rng)
        kind, detail = outcome(data, chosen)
        counts[kind] += 1
        for mutation in how.split("; "):
            mutations[mutation.split(" at ")[0].split(" of ")[0]] += 1
        if kind.startswith("refused"):
            reasons[f"{kind}: {detail}" if detail else kind] += 1
        if kind == "violation" and len(violations) < KEPT:
            violations.append(
                {"case": case, "seed file": chosen.name, "mutation": how, "what": detail}
            )
    return {
        "cases": cases,
        "seed": seed,
        "first case": first,
        "seed files": len(seeds),
        "seconds": round(time.perf_counter() - started, 1),
        **{
            kind: counts[kind]
            for kind in (
                "loaded_same",
                "loaded_different",
                "refused_name",
                "refused_cut_short",
                "refused_content",
                "violation",
            )
        },
        "most common refusals": dict(reasons.most_common(KEPT)),
        "violations": violations,
    }


def main(argv: list[str] | None = None) -> int:
    """Run the cases the arguments name; print the counts as JSON; 1 if any violated."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=10_000, help="how many cases (10,000)")
    parser.add_argument("--seed", type=int, default=0, help="the run's seed (0)")
    parser.add_argument("--first", type=int, default=0, help="the first case's number (0)")
    parser.add_argument("--case", type=int, help="run this one case and describe it")
    parser.add_argument(
        "--address-space",
        type=int,
        default=2048,
        help="MiB more address space the run may map than it has at its start (2048)",
    )
    args = parser.parse_args(argv)
    limit_address_space(args.address_space)
    if args.case is not None:
        seeds = make_seeds()
        rng = np.random.default_rng([args.seed, args.case])
        chosen = seeds[int(rng.integers(len(seeds)))]
        data, how = mutated(chosen, seeds, rng)
        kind, detail = outcome(data, chosen)
        print(
            json.dumps(
                {
                    "case": args.case,
                    "seed file": chosen.name,
                    "mutation": how,
                    "bytes": len(data),
                    "outcome": kind,
                    "detail": detail,
                },
                indent=1,
            )
        )
        return 1 if kind == "violation" else 0
    report = run(args.cases, args.seed, args.first)
    print(json.dumps(report, indent=1))
    return 1 if report["violation"] else 0


if __name__ == "__main__":
    sys.exit(main())
