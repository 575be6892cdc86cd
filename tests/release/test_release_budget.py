"""The release reader's memory budget: a file's pickles may make at most 64 bytes of objects a
byte of the file and 1 MiB. A 1 MB file that encodes one memoized string 3,000 times (3 GB of
bytes unchecked) is refused in one line by `links import-release`, whose peak resident memory
stays within 200 MiB of an empty import's; a million nested lists are refused within their
budget; the grammar fuzzer's files load or are refused in one line, within their budgets."""

from __future__ import annotations

import io
import pickle
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import links_ray
from links_ray.bench.pickle_fuzz import format_pickle_fuzz, fuzz_examples
from links_ray.release.opcode_scan import memory_budget
from links_ray.release.pickles import ReleaseFileError, read_pickles

#: The checkout whose links_ray these tests import, for the child processes they start.
CHECKOUT = Path(links_ray.__file__).resolve().parents[1]
#: Runs `links import-release argv[1] --out argv[2]` in a child and prints its exit status,
#: its peak resident memory (bytes) and its stderr's last line.
PEAK_OF_IMPORT = """
import resource, subprocess, sys
done = subprocess.run(
    [sys.executable, "-m", "links_ray.cli", "import-release", sys.argv[1], "--out", sys.argv[2]],
    capture_output=True, text=True, timeout=600,
)
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024
print(done.returncode, peak, (done.stderr.strip().splitlines() or [""])[-1], sep="\\n")
"""


def encoded_again(length: int, times: int) -> bytes:
    """A protocol 2 pickle of a list holding a memoized string of `length` characters encoded
    to latin-1 `times` times, each in 8 bytes of the file."""
    text = b"x" * length
    return b"".join(
        [
            b"\x80\x02c_codecs\nencode\nq\x00",
            b"X" + length.to_bytes(4, "little") + text + b"q\x01",
            b"X\x06\x00\x00\x00latin1q\x02",
            b"]q\x03(" + b"h\x00h\x01h\x02\x86R" * times + b"e.",
        ]
    )


def traced_read(data: bytes) -> tuple[str, int]:
    """(the refusal or "loaded", traced peak bytes) of reading `data` as a release file."""
    warm = pickle.dumps([np.arange(3.0)], 4)  # what the first read loads is not the file's
    list(read_pickles(io.BytesIO(warm), "warm", len(warm)))
    tracemalloc.start()
    try:
        try:
            list(read_pickles(io.BytesIO(data), "crafted", len(data)))
            said = "loaded"
        except ReleaseFileError as exc:
            said = str(exc)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return said, peak


def peak_of_import(src: Path, out: Path) -> tuple[int, int, str]:
    """(exit status, peak resident bytes, last line of stderr) of `links import-release`."""
    done = subprocess.run(
        [sys.executable, "-c", PEAK_OF_IMPORT, str(src), str(out)],
        capture_output=True,
        text=True,
        timeout=900,
        cwd=CHECKOUT,
        check=True,
    )
    status, peak, line = done.stdout.split("\n", 2)
    return int(status), int(peak), line.strip()


def test_a_string_encoded_3000_times_is_refused_without_amplifying_memory(tmp_path: Path) -> None:
    data = encoded_again(1_000_000, 3000)
    assert 1_020_000 < len(data) < 1_030_000
    budget = 64 * len(data) + 2**20
    said, peak = traced_read(data)
    assert said == (
        f"crafted batch 0 at byte 0 is not a readable pickle: its objects would take more than "
        f"{budget:,} bytes of memory, the budget of a file of {len(data):,} bytes (64 a byte "
        f"and 1,048,576)"
    )
    # Unchecked, the encodings took 3 GB; the reader's own buffers take up to 3 times the file.
    assert peak <= budget + 3 * len(data) + 2**20, peak
    (tmp_path / "crafted").mkdir()
    (tmp_path / "crafted" / "dataset").write_bytes(data)
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "dataset").write_bytes(pickle.dumps([], 4))
    status, empty_peak, _ = peak_of_import(tmp_path / "empty", tmp_path / "empty_root")
    assert status == 0
    status, crafted_peak, line = peak_of_import(tmp_path / "crafted", tmp_path / "crafted_root")
    print(f"peak RSS: empty import {empty_peak >> 20} MiB, crafted {crafted_peak >> 20} MiB")
    assert status == 2
    assert line.startswith(f"links import-release: error: {tmp_path}/crafted/dataset batch 0 ")
    assert line.endswith("(64 a byte and 1,048,576)")
    assert crafted_peak - empty_peak < 200 * 2**20


def test_encodings_within_the_budget_load() -> None:
    # 30 encodings of 10,000 characters are within a 10 KB file's budget, 1.7 MB; 300 are not.
    data = encoded_again(10_000, 30)
    said, peak = traced_read(data)
    assert said == "loaded"
    (batch,) = [value for _, _, value in read_pickles(io.BytesIO(data), "x", len(data))]
    assert batch == [b"x" * 10_000] * 30
    assert peak <= memory_budget(len(data))
    said, _ = traced_read(encoded_again(10_000, 300))
    assert "its objects would take more than" in said


@pytest.mark.parametrize("depth", [1_000_000])
def test_deeply_nested_lists_are_refused_within_their_budget(depth: int) -> None:
    data = b"\x80\x02" + b"]" * depth + b"a" * (depth - 1) + b"."
    said, peak = traced_read(data)
    assert said.endswith(
        f"its objects would take more than {memory_budget(len(data)):,} bytes of memory, the "
        f"budget of a file of {len(data):,} bytes (64 a byte and 1,048,576)"
    )
    assert peak <= memory_budget(len(data)) + 3 * len(data) + 2**20


def test_the_grammar_fuzzers_files_load_or_are_refused_within_their_budgets() -> None:
    result = fuzz_examples(120, seed=0)
    print(format_pickle_fuzz(result))
    assert result["inputs"] == 120
    assert result["crash"] == 0 and result["over_budget"] == 0, result["examples"]
    assert result["loaded"] + result["refused"] == 120
    assert result["loaded"] > 0 and result["refused"] > result["refused_by_budget"] > 0
