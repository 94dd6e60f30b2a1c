"""Making cleanup unconditional: termination signals become KeyboardInterrupt so `finally` and `__exit__` run.

atexit handlers do not run on SIGTERM, and a process killed by an unhandled SIGTERM skips every `finally`,
which would leave a laser emitting. Inside `signals_interrupt()` a SIGTERM or SIGHUP raises KeyboardInterrupt
in the main thread instead, so the laser's context manager turns emission off on the way out.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator

TERMINATION_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


class TerminatedBySignal(KeyboardInterrupt):
    """A termination signal arrived; handled like Ctrl-C so the same cleanup runs."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"terminated by {signal.Signals(signum).name}")
        self.signum = signum


def _raise(signum: int, _frame: object) -> None:
    raise TerminatedBySignal(signum)


@contextmanager
def signals_interrupt() -> Iterator[None]:
    """While the block runs, SIGTERM and SIGHUP raise TerminatedBySignal (a KeyboardInterrupt)."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be installed from the main thread
        return
    previous = {sig: signal.signal(sig, _raise) for sig in TERMINATION_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
