"""A plain-text progress bar with an estimate of the time left, on stderr.

On a terminal the bar is redrawn in place; otherwise (a log file, CI) a line is printed only
every tenth of the work or every minute, so logs stay short.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


def format_duration(seconds: float) -> str:
    seconds = max(0.0, seconds)
    if seconds < 60:
        return f"{seconds:.0f}s"
    minutes, secs = divmod(round(seconds), 60)
    if minutes < 60:
        return f"{minutes}m{secs:02d}s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h{minutes:02d}m"


class Progress:
    """Counts finished jobs; ``done`` of ``total`` were finished before this session."""

    WIDTH = 30
    LOG_EVERY_SECONDS = 60.0

    def __init__(
        self, total: int, done: int = 0, stream: TextIO | None = None, label: str = "jobs"
    ) -> None:
        self.total = total
        self.done = done
        self.resumed = done
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.interactive = bool(getattr(self.stream, "isatty", lambda: False)())
        self.started = time.monotonic()
        self._last_line = self.started
        self._last_tenth = -1
        self._drawn = 0

    def seconds_left(self) -> float | None:
        """Time left at the rate of this session (None before the first job finishes)."""
        finished_now = self.done - self.resumed
        if finished_now <= 0:
            return None
        rate = (time.monotonic() - self.started) / finished_now
        return rate * (self.total - self.done)

    def line(self) -> str:
        fraction = self.done / self.total if self.total else 1.0
        filled = round(fraction * self.WIDTH)
        bar = "#" * filled + "." * (self.WIDTH - filled)
        elapsed = format_duration(time.monotonic() - self.started)
        left = self.seconds_left()
        eta = "estimating" if left is None else f"~{format_duration(left)} left"
        if self.done >= self.total:
            eta = "done"
        return (
            f"[{bar}] {self.done}/{self.total} {self.label} {100 * fraction:3.0f}%  "
            f"elapsed {elapsed}  {eta}"
        )

    def start(self) -> None:
        if self.resumed:
            self._write(f"resuming: {self.resumed} of {self.total} {self.label} already done")
        self._show(force=True)

    def advance(self, count: int = 1) -> None:
        self.done += count
        self._show(force=self.done >= self.total)

    def finish(self) -> None:
        if self.interactive:
            self.stream.write("\n")
            self.stream.flush()

    def _show(self, force: bool = False) -> None:
        if self.interactive:
            line = self.line()
            # Pad over the rest of a longer previous line.
            self.stream.write("\r" + line.ljust(self._drawn))
            self._drawn = len(line)
            self.stream.flush()
            return
        now = time.monotonic()
        tenth = int(10 * self.done / self.total) if self.total else 10
        if force or tenth > self._last_tenth or now - self._last_line >= self.LOG_EVERY_SECONDS:
            self._write(self.line())
            self._last_line = now
        self._last_tenth = max(self._last_tenth, tenth)

    def _write(self, text: str) -> None:
        if self.interactive:
            text = "\r" + text
        self.stream.write(text + "\n")
        self.stream.flush()
