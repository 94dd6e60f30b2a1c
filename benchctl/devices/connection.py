"""Open / close bookkeeping shared by the SLM and the camera: idempotent, a context manager, and the device's
lock held from open to close (one command at a time uses a device)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TypeVar

from benchctl.devices.lock import DeviceLock

T = TypeVar("T", bound="Connection")


class Connection(ABC):
    """A device that is opened once and closed once, however often open() and close() are called."""

    _open_now = False
    _hold: DeviceLock | None = None

    @abstractmethod
    def _device_lock(self) -> DeviceLock:
        """The lock that names this device (its port, device file or USB id)."""

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
        """Lock the device, then connect (no-op if open); returns self. Held by another command: DeviceHeld."""
        if not self._open_now:
            hold = self._device_lock().acquire()
            try:
                self._open()
            except BaseException:
                hold.release()
                raise
            self._hold = hold
            self._open_now = True
        return self

    def close(self) -> None:
        """Disconnect (no-op if closed)."""
        if self._open_now:
            self._open_now = False
            try:
                self._close()
            finally:
                if self._hold is not None:
                    self._hold.release()
                    self._hold = None

    def __enter__(self: T) -> T:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()
