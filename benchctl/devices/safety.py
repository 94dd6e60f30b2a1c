"""Making cleanup unconditional: termination signals become KeyboardInterrupt so `finally` and `__exit__` run.

atexit handlers do not run on SIGTERM, and a process killed by an unhandled SIGTERM skips every `finally`,
which would leave a laser emitting. Inside `signals_interrupt()` a SIGTERM or SIGHUP raises KeyboardInterrupt
in the main thread instead, so the laser's context manager turns emission off on the way out.

The kernel may hand a process-wide signal to any thread that does not block it (torch's worker threads, a
simulator's thread). Python then runs the handler in the main thread only when that thread next runs Python
code, and a plain `time.sleep` in the main thread is not woken: a 30 s camera readout, or `laser on` holding
emission, would carry on. Device waits therefore use `wait()`, which also wakes on the signal wakeup file
descriptor that the C-level handler writes to from whichever thread received the signal, and which raises a
termination signal found there even when its handler's exception was lost in C code (`wait`'s docstring).
"""

from __future__ import annotations

import select
import signal
import socket
import threading
import time
from contextlib import contextmanager
from typing import Iterator

TERMINATION_SIGNALS = (signal.SIGTERM, signal.SIGHUP)

_wakeup: socket.socket | None = None
"""The reading end of the signal wakeup socket while `signals_interrupt()` is active in the main thread."""


class TerminatedBySignal(KeyboardInterrupt):
    """A termination signal arrived; handled like Ctrl-C so the same cleanup runs."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"terminated by {signal.Signals(signum).name}")
        self.signum = signum


def _raise(signum: int, _frame: object) -> None:
    raise TerminatedBySignal(signum)


@contextmanager
def signals_interrupt() -> Iterator[None]:
    """While the block runs, SIGTERM and SIGHUP raise TerminatedBySignal (a KeyboardInterrupt), and `wait()`
    returns early when any signal arrives, whichever thread the kernel delivered it to."""
    global _wakeup
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be installed from the main thread
        return
    reader, writer = socket.socketpair()
    reader.setblocking(False)
    writer.setblocking(False)
    previous = {sig: signal.signal(sig, _raise) for sig in TERMINATION_SIGNALS}
    previous_fd = signal.set_wakeup_fd(writer.fileno(), warn_on_full_buffer=False)
    outer, _wakeup = _wakeup, reader
    try:
        yield
    finally:
        _wakeup = outer
        signal.set_wakeup_fd(previous_fd)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        reader.close()
        writer.close()


def wait(seconds: float) -> None:
    """Sleep `seconds`, returning early only to let a signal's handler run (it raises for SIGTERM, SIGHUP and
    Ctrl-C); outside `signals_interrupt()`, or off the main thread, this is `time.sleep`.

    A termination signal or Ctrl-C that arrived since the last wait always ends it, even when its handler's
    exception was lost: a handler runs at whatever Python code the main thread is executing, and C code that
    called that Python code may discard the exception (seen: a SIGTERM landing in the ABC registration of a
    lazily imported numpy.random). The wakeup descriptor still holds the signal's number, so it is raised here.
    """
    if _wakeup is None or threading.current_thread() is not threading.main_thread():
        time.sleep(seconds)
        return
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        ready, _, _ = select.select([_wakeup], [], [], left)
        if ready:
            arrived = _drain(_wakeup)
            signal.pthread_kill(threading.get_ident(), 0)  # runs the handlers still pending, before raising here
            _raise_lost(arrived)


def _drain(reader: socket.socket) -> bytes:
    """Everything the signal wakeup descriptor holds: one byte per signal, its number."""
    arrived = bytearray()
    try:
        while chunk := reader.recv(64):
            arrived += chunk
    except BlockingIOError:
        pass
    return bytes(arrived)


def _raise_lost(arrived: bytes) -> None:
    """Raise what the handler of a termination signal or Ctrl-C among `arrived` should have raised."""
    for signum in arrived:
        if signum in TERMINATION_SIGNALS:
            raise TerminatedBySignal(signum)
        if signum == signal.SIGINT and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            raise KeyboardInterrupt
