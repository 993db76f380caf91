"""A one-line progress report on stderr (runs done / total, elapsed, ETA) with no extra dependencies.

On a terminal the line is redrawn in place; otherwise (CI logs, pipes) only the final line is
written, so logs are not flooded with carriage returns.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


def format_duration(seconds: float) -> str:
    """``seconds`` as h:mm:ss or m:ss."""
    whole = max(0, round(seconds))
    hours, rest = divmod(whole, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


class Progress:
    """Counts finished units of work and reports them; ``finish()`` writes the closing line."""

    def __init__(self, total: int, label: str = "runs", stream: TextIO | None = None) -> None:
        self.total = total
        self.label = label
        self.stream = sys.stderr if stream is None else stream
        self.done = 0
        self.started = time.perf_counter()
        isatty = getattr(self.stream, "isatty", None)
        self.live = bool(isatty and isatty())
        if self.live:
            self._draw()

    def advance(self, count: int = 1) -> None:
        """Record ``count`` more finished units and redraw the line on a terminal."""
        self.done += count
        if self.live:
            self._draw()

    def finish(self) -> None:
        """Write the final line (always, terminal or not)."""
        elapsed = time.perf_counter() - self.started
        line = f"{self.label} {self.done}/{self.total} done in {format_duration(elapsed)}"
        self.stream.write(("\r\x1b[K" if self.live else "") + line + "\n")
        self.stream.flush()

    def _draw(self) -> None:
        elapsed = time.perf_counter() - self.started
        if self.done:
            eta = format_duration(elapsed / self.done * (self.total - self.done))
        else:
            eta = "?"
        line = f"{self.label} {self.done}/{self.total}  elapsed {format_duration(elapsed)}  ETA {eta}"
        self.stream.write("\r\x1b[K" + line)
        self.stream.flush()
