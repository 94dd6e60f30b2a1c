"""Open / close bookkeeping shared by the SLM and the camera: idempotent, and a context manager."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TypeVar

T = TypeVar("T", bound="Connection")


class Connection(ABC):
    """A device that is opened once and closed once, however often open() and close() are called."""

    _open_now = False

    @abstractmethod
    def _open(self) -> None:
        """Connect to the device."""

    @abstractmethod
    def _close(self) -> None:
        """Release the device; must not raise for a device that is already gone."""

    @property
    def is_open(self) -> bool:
        """Whether the device is connected now."""
        return self._open_now

    def open(self: T) -> T:
        """Connect (no-op if open); returns self."""
        if not self._open_now:
            self._open()
            self._open_now = True
        return self

    def close(self) -> None:
        """Disconnect (no-op if closed)."""
        if self._open_now:
            self._open_now = False
            self._close()

    def __enter__(self: T) -> T:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()
