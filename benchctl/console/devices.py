"""The devices the console holds: each opened once through its driver (which takes the device's lock, so the
console is one holder like any command) and used by one thread at a time.

A device held by another program (a run, `benchctl laser on`) is not an error for the console as a whole: its
panel says who holds it, and `connect` tries again. `release` lets go (a procedure started from the console
needs the devices it uses).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Generic, TypeVar

from benchctl.errors import BenchctlError

T = TypeVar("T")


class Held(Generic[T]):
    """One device: `opener` opens it through its driver; `closer` closes it (the laser's close switches emission
    off); `use()` gives it to one thread at a time."""

    def __init__(self, name: str, opener: Callable[[], T], closer: Callable[[T], None]) -> None:
        self.name = name
        self._opener = opener
        self._closer = closer
        self._lock = threading.RLock()
        self.device: T | None = None
        self.error: str | None = None  # why it is not connected (held by another program, not found, ...)

    @property
    def connected(self) -> bool:
        return self.device is not None

    def connect(self) -> bool:
        """Open the device unless it is open; False (and `error` says why) when it cannot be opened now."""
        with self._lock:
            if self.device is None:
                try:
                    self.device = self._opener()
                    self.error = None
                except BenchctlError as exc:
                    self.error = str(exc)
            return self.device is not None

    def release(self) -> None:
        """Close the device (its driver's close: a laser switches emission off); raises what closing raised."""
        with self._lock:
            device, self.device = self.device, None
            if device is not None:
                self.error = "released by the console"
                self._closer(device)

    def lost(self, reason: str) -> None:
        """The device stopped working (its X server went away, its cable was pulled): close what is left of it
        (errors on the way are the loss itself) and keep `reason` for the page, which offers to connect again."""
        with self._lock:
            device, self.device = self.device, None
            self.error = reason
            if device is not None:
                try:
                    self._closer(device)
                except Exception:  # noqa: BLE001 - a device that is gone fails to close; nothing is left to do
                    pass

    @contextmanager
    def use(self) -> Iterator[T]:
        """The open device, for this thread alone until the block ends; BenchctlError when it is not connected
        (never reconnected here: a device let go for a run stays free until the console connects it again)."""
        with self._lock:
            if self.device is None:
                raise BenchctlError(f"{self.name} not connected: {self.error}")
            assert self.device is not None
            yield self.device
