"""The progress meter of long runs: one line rewritten in place on a terminal, a line a minute
in a log, each with the count, the rate and the time left (a clock of the test's own)."""

from __future__ import annotations

import io

import pytest

from links_ray.cluster import progress
from links_ray.cluster.progress import LINE_EVERY_S, Progress, duration


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    now = [1000.0]
    monkeypatch.setattr(progress.time, "monotonic", lambda: now[0])
    return now


def test_a_log_gets_a_line_a_minute(clock: list[float]) -> None:
    log = io.StringIO()
    meter = Progress(total=1_000_000, unit="mechanisms", stream=log)
    for _ in range(600):  # ten minutes, a shard of 1,000 every second
        clock[0] += 1.0
        meter.advance(1_000)
    meter.close()
    lines = log.getvalue().splitlines()
    # The first shard's line, then one each LINE_EVERY_S, then the last count at the close.
    done = [int(line.split("/")[0].replace(",", "")) for line in lines]
    every = int(LINE_EVERY_S)
    assert done == [1_000 * s for s in range(1, 601, every)] + [600_000]
    assert lines[-1] == "600,000/1,000,000 mechanisms (60%), 1,000 mechanisms/s, 6 min 40 s left"
    assert "\r" not in log.getvalue()


def test_a_terminal_gets_one_line_updated_in_place(clock: list[float]) -> None:
    screen = Terminal()
    meter = Progress(total=20_000_000, done=5_000_000, unit="mechanisms", stream=screen)
    for _ in range(10):
        clock[0] += 1.0
        meter.advance(8_000)
    meter.close()
    shown = screen.getvalue()
    assert shown.count("\n") == 1 and shown.endswith("\n")
    updates = shown.split("\r")[1:]
    assert len(updates) == 12  # the resumed count, ten advances, the close
    assert updates[-1].startswith("[#######-----------------------] 5,080,000/20,000,000")
    assert "8,000 mechanisms/s, 31 min 05 s left" in updates[-1]


@pytest.mark.parametrize(
    ("seconds", "text"),
    [(0.4, "0 s"), (42, "42 s"), (425, "7 min 05 s"), (10_920, "3 h 02 min"), (3600, "1 h 00 min")],
)
def test_durations_read_as_a_person_reads_them(seconds: float, text: str) -> None:
    assert duration(seconds) == text


def test_a_total_known_as_the_work_goes_is_shown_as_an_estimate(clock: list[float]) -> None:
    """An import of the release learns its total as it reads: none at first, then estimates
    ("~"), then the total; a failed run ends its line without a final count."""
    log = io.StringIO()
    meter = Progress(total=None, unit="mechanisms", stream=log)
    clock[0] += 2.0
    meter.advance(1_000)
    meter.estimate(9_000)
    clock[0] += LINE_EVERY_S
    meter.advance(2_000)
    meter.estimate(6_000, exact=True)
    meter.close()
    assert log.getvalue().splitlines() == [
        "1,000 mechanisms, 500 mechanisms/s, total not yet known",
        "3,000/~9,000 mechanisms (33%), 48 mechanisms/s, 2 min 04 s left",
        "3,000/6,000 mechanisms (50%), 48 mechanisms/s, 1 min 02 s left",
    ]
    screen = Terminal()
    failed = Progress(total=None, unit="mechanisms", stream=screen)
    clock[0] += 1.0
    failed.advance(10)
    failed.close(final=False)
    assert screen.getvalue() == (
        "\r[------------------------------] 10 mechanisms, 10 mechanisms/s, total not yet known"
        "\033[K\n"
    )
