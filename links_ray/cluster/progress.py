"""A dependency-free progress meter: one line updated in place on a terminal (a bar, the count,
the rate and the time left), and the same line once a minute in logs."""

from __future__ import annotations

import sys
import time
from typing import TextIO

#: Seconds between plain progress lines when the output is not a terminal (a log).
LINE_EVERY_S = 60.0
#: Seconds between updates of the line on a terminal.
LIVE_EVERY_S = 0.2


def duration(seconds: float) -> str:
    """`seconds` as a person reads a time left: "42 s", "7 min 05 s", "3 h 02 min"."""
    whole = round(seconds)
    hours, rest = divmod(whole, 3600)
    minutes, secs = divmod(rest, 60)
    if hours:
        return f"{hours} h {minutes:02d} min"
    if minutes:
        return f"{minutes} min {secs:02d} s"
    return f"{secs} s"


class Progress:
    """Counts work done towards `total` and shows the rate and the time left. A total known
    only as the work goes (`estimate`) is None until there is one, then shown with a "~"."""

    def __init__(
        self,
        total: int | None,
        done: int = 0,
        unit: str = "items",
        enabled: bool = True,
        stream: TextIO | None = None,
    ) -> None:
        self.total = total
        self.exact = True
        self.done = done
        self.unit = unit
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.live = enabled and self.stream.isatty()
        self._start_done = done
        self._start = time.monotonic()
        self._shown = 0.0
        if done and enabled:
            self._show(force=True)

    def advance(self, amount: int) -> None:
        """Count `amount` more items done and show progress if it is time to."""
        self.done += amount
        self._show()

    def estimate(self, total: int | None, exact: bool = False) -> None:
        """Set the total as far as it is known: None while it is not, an estimate, or (with
        `exact`) the total."""
        self.total = total
        self.exact = exact

    def _rate(self) -> float:
        elapsed = time.monotonic() - self._start
        return (self.done - self._start_done) / elapsed if elapsed > 0 else 0.0

    def line(self) -> str:
        """Done of total, the share, the rate in units a second and the seconds left."""
        rate = self._rate()
        if self.total is None:
            return f"{self.done:,} {self.unit}, {rate:,.0f} {self.unit}/s, total not yet known"
        left = max(self.total - self.done, 0)
        eta = f"{duration(left / rate)} left" if rate > 0 else "estimating"
        share = min(self.done / self.total, 1.0) if self.total else 1.0
        about = "" if self.exact else "~"
        return (
            f"{self.done:,}/{about}{self.total:,} {self.unit} ({share:.0%}), "
            f"{rate:,.0f} {self.unit}/s, {eta}"
        )

    def _show(self, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if self.live:
            if force or now - self._shown >= LIVE_EVERY_S:
                width = 30
                if self.total is None:
                    filled = 0  # no total yet: an empty bar
                elif self.total:
                    filled = min(int(width * self.done / self.total), width)
                else:
                    filled = width
                bar = "#" * filled + "-" * (width - filled)
                self.stream.write(f"\r[{bar}] {self.line()}\033[K")
                self.stream.flush()
                self._shown = now
        elif force or now - self._shown >= LINE_EVERY_S:
            self.stream.write(self.line() + "\n")
            self.stream.flush()
            self._shown = now

    def close(self, final: bool = True) -> None:
        """Show the final count (unless not `final`: a run that failed says why instead) and
        end a live bar's line."""
        if not self.enabled:
            return
        if final:
            self._show(force=True)
        if self.live:
            self.stream.write("\n")
            self.stream.flush()
