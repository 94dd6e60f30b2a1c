"""Holograms for the SLM panel, computed in a worker process so that the console's own process stays responsive.

A 50-iteration SGD at full size keeps the cores busy for a minute. In the console's process its Python work would
compete with the event loop for the GIL and its torch threads with the live view for the cores (status requests
waited up to 0.27 s, docs/console.md). The worker is one child process, `python -m benchctl.console.holograms` (a
fresh interpreter: the console has threads, and a script that embeds the console is never run again), started on
the first hologram and kept until the console stops; requests and results travel as pickles over a socket pair.
It leaves one core to the console's own process (WORKER_THREADS) and runs at a slightly lower priority
(WORKER_NICE), so the live view keeps its pace; docs/console.md has the measurements behind both. It runs what a
run runs (`holograms.cache.hologram`: the same method, calibration, fitted model and cache) and reports its
progress as it goes. It holds no device.
"""

from __future__ import annotations

import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from benchctl.errors import BenchctlError

WORKER_NICE = 2  # added to the console's own niceness
WORKER_THREADS = max(1, len(os.sched_getaffinity(0)) - 1) if hasattr(os, "sched_getaffinity") else 1


@dataclass(frozen=True)
class Request:
    """One hologram: the target plane amplitude (3, H, W) on the SLM grid and how to compute it."""

    profile: Any  # benchctl.profiles.Profile (calibration applied)
    amplitude: Any  # torch.Tensor
    channel: str
    method: str
    iterations: int | None
    seed: int
    checkpoint: str | None


@dataclass(frozen=True)
class Result:
    """The frame as displayed (gray levels), the simulated reconstruction's scores, seconds, from the cache or not."""

    gray: np.ndarray
    scores: dict[str, float]
    seconds: float
    cached: bool


class HologramWorker:
    """The console's hologram process; `compute` runs one request in it (one at a time), `close` ends it."""

    def __init__(self) -> None:
        self._process: subprocess.Popen[bytes] | None = None
        self._connection: Connection | None = None
        self._lock = threading.Lock()

    def compute(self, request: Request, progress: Callable[[str, int, int], None] | None = None) -> Result:
        """`request` computed in the worker (started if it is not running); `progress(label, done, total)` as it
        goes. The worker's BenchctlError is raised here as it is; a worker that died is said in one line."""
        with self._lock:
            connection = self._start()
            try:
                _send(connection, request)
                while True:
                    kind, *message = _receive(connection)
                    if kind == "progress" and progress is not None:
                        progress(*message)
                    elif kind == "done":
                        return message[0]
                    elif kind == "error":
                        raise message[0]
            except (EOFError, OSError):
                self._stop()
                raise BenchctlError("the hologram worker process ended while computing (out of memory, or the "
                                    "console is stopping); try again") from None

    def close(self) -> None:
        """End the worker (at once if it is computing)."""
        self._stop()

    def _start(self) -> Connection:
        if self._process is None or self._process.poll() is not None:
            ours, theirs = socket.socketpair()
            with theirs:
                self._process = subprocess.Popen(
                    [sys.executable, "-m", "benchctl.console.holograms", str(theirs.fileno()), str(WORKER_NICE),
                     str(WORKER_THREADS)], pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL)
            self._connection = Connection(ours.detach())
        assert self._connection is not None
        return self._connection

    def _stop(self) -> None:
        process, connection, self._process, self._connection = self._process, self._connection, None, None
        if connection is not None:
            connection.close()  # an idle worker reads the end of its socket and exits
        if process is not None:
            try:
                process.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                process.terminate()
                process.wait(timeout=5.0)


def _serve(connection: Connection, nice: int, threads: int) -> None:
    """The worker's loop: a Request in, progress messages and then its Result (or its error) out."""
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C in the console's terminal is the console's to handle
    os.nice(nice)
    torch.set_num_threads(threads)
    while True:
        try:
            request = _receive(connection)
        except (EOFError, OSError):
            return
        try:
            _send(connection, ("done", _compute(request, connection)))
        except Exception as exc:
            try:
                _send(connection, ("error", exc if isinstance(exc, BenchctlError) else BenchctlError(
                    f"hologram: {type(exc).__name__}: {exc}")))
            except Exception:  # an error that does not pickle: its line
                _send(connection, ("error", BenchctlError(f"hologram: {exc}")))


def _send(connection: Connection, message: Any) -> None:
    """One message, pickled plainly (multiprocessing's own pickler would hand tensors over as shared memory, which
    only a process multiprocessing started may open)."""
    connection.send_bytes(pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL))


def _receive(connection: Connection) -> Any:
    return pickle.loads(connection.recv_bytes())


def _compute(request: Request, connection: Connection) -> Result:
    from benchctl.calibration.calibrated import Calibrated
    from benchctl.holograms.cache import hologram

    def progress(label: str) -> Callable[[int, int], None]:
        return lambda done, total: _send(connection, ("progress", label, done, total))

    result = hologram(Calibrated(request.profile), request.amplitude, request.channel, request.method,
                      iterations=request.iterations, seed=request.seed, checkpoint=request.checkpoint,
                      progress=progress)
    return Result(result.gray, result.scores, result.seconds, result.cached)


if __name__ == "__main__":
    from benchctl.console.holograms import _serve as serve  # this module by its name, as the console pickles it

    serve(Connection(int(sys.argv[1])), int(sys.argv[2]), int(sys.argv[3]))
