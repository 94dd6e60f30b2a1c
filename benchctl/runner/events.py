"""`benchctl run --events FD`: the run's events as JSON lines on an open file descriptor, for a program that follows
the run (the console) without parsing what it prints.

One JSON object per line, as each happens: `{"event": "run", "folder": ..., "steps": N, "resumed": bool}` once the
run folder is created or reopened; then every event of the run's step log as it is written (`start`, `done`,
`failed`, `interrupted`, `invalid`, ... with `step`, as steps.jsonl has them); last `{"event": "stop", "status":
"finished" | "failed" | "interrupted", ...}`, the run's stop record. A run that fails before it has a folder sends
nothing: its exit status and its one line say why. The stream is a courtesy, the step log the record: a reader that
goes away stops the stream, never the run.
"""

from __future__ import annotations

import json
import os
from typing import IO, Any

from benchctl.errors import BenchctlError


class EventStream:
    """The writer of `--events FD` (called with each event)."""

    def __init__(self, fd: int) -> None:
        try:
            self._file: IO[str] | None = os.fdopen(fd, "w", encoding="utf-8", closefd=False)
        except OSError as exc:
            raise BenchctlError(f"--events {fd}: not an open file descriptor ({exc.strerror or exc})") from None

    def __call__(self, event: dict[str, Any]) -> None:
        if self._file is None:
            return
        try:
            self._file.write(json.dumps(event, default=str) + "\n")
            self._file.flush()
        except OSError:  # the reader went away (or the descriptor was not writable): the run goes on
            self._file = None
