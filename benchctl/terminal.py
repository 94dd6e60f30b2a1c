"""Terminal output for long work: a progress line on stderr that stays quiet when nobody is watching."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class ProgressLine:
    """Callable `progress(done, total)` that redraws one line on a terminal, or logs every 25 % otherwise."""

    def __init__(self, label: str, stream: TextIO | None = None, width: int = 30) -> None:
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.width = width
        self._start = time.perf_counter()
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last_quarter = -1

    def __call__(self, done: int, total: int) -> None:
        elapsed = time.perf_counter() - self._start
        if self._tty:
            filled = int(self.width * done / max(total, 1))
            bar = "#" * filled + "." * (self.width - filled)
            end = "\n" if done >= total else ""
            self.stream.write(f"\r{self.label} [{bar}] {done}/{total} {elapsed:.1f}s{end}")
            self.stream.flush()
            return
        quarter = 4 * done // max(total, 1)
        if quarter > self._last_quarter:
            self._last_quarter = quarter
            self.stream.write(f"{self.label}: {done}/{total} ({elapsed:.1f}s)\n")
            self.stream.flush()
