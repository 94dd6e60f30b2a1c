"""pyserial's handler for `sim://` URLs: a serial port wired to one of benchctl's byte-level emulators (the lasers,
and the Zaber focus stage with `dialect=zaber`).

    sim://<device-name>?dialect=template|cobolt|obis|zaber&fault=a,b&reply_delay_s=0.1&max_mw=40&channels=3

pyserial imports this module (package benchctl.devices.sim, added to serial.protocol_handler_packages by
serial_link) and uses its `Serial` class. Keep its imports light and safe: an ImportError raised here shows up
only as "protocol 'sim' not known".

Replies become readable reply_delay_s after the command that caused them, in order; reset_input_buffer discards
what has arrived, not what is still on its way, as on a real line. While open, the port holds the device's
DeviceLock: a second open fails with a SerialException carrying errno EBUSY, like a busy tty.
"""

from __future__ import annotations

import errno
import threading
import time
from collections import deque
from typing import TYPE_CHECKING, Any, Protocol
from urllib.parse import parse_qsl, urlsplit

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from benchctl.devices.errors import DeviceBusy
from benchctl.devices.lock import DeviceLock
from benchctl.devices.sim.laser_emulators import make_emulator
from benchctl.devices.sim.state import sim_lock

if TYPE_CHECKING:
    from _typeshed import ReadableBuffer


def parse_url(url: str) -> tuple[str, dict[str, str]]:
    """(device name, parameters) of a sim:// URL; SerialException if it is not one."""
    parts = urlsplit(url)
    if parts.scheme.lower() != "sim" or not parts.netloc:
        raise SerialException(f"expected sim://<device-name>?<options>, got {url!r}")
    try:
        params = dict(parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query)))
    except ValueError as exc:
        raise SerialException(f"{url}: cannot read the options: {exc}") from None
    return parts.netloc, params


class Emulator(Protocol):
    """What the port needs of a device at its other end: bytes in, reply bytes out, and the reply delay."""

    reply_delay_s: float

    def receive(self, data: bytes) -> bytes: ...


def make_device(name: str, params: dict[str, str]) -> Emulator:
    """The emulator a sim:// URL names; ValueError names a bad option."""
    if params.get("dialect") == "zaber":
        from benchctl.devices.sim.zaber_stage import ZaberStage

        return ZaberStage(name, {k: v for k, v in params.items() if k != "dialect"})
    return make_emulator(name, params)


class Serial(SerialBase):
    """A serial port whose other end is a simulated laser unit (see the module docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:  # SerialBase's own arguments
        self._device: Emulator | None = None
        self._hold: DeviceLock | None = None
        self._arrived = bytearray()
        self._in_flight: deque[tuple[float, bytes]] = deque()  # (time it arrives, bytes), in order
        self._changed = threading.Condition()
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self.port is None:
            raise SerialException("Port must be configured before it can be used.")
        name, params = parse_url(self.port)
        hold = sim_lock(name)
        try:
            hold.acquire()
        except DeviceBusy as exc:
            raise SerialException(errno.EBUSY, str(exc)) from None
        try:
            self._device = make_device(name, params)
        except ValueError as exc:
            hold.release()
            raise SerialException(str(exc)) from None
        except BaseException:
            hold.release()
            raise
        self._hold = hold
        self._arrived.clear()
        self._in_flight.clear()
        self.is_open = True

    def close(self) -> None:
        if self.is_open:
            self.is_open = False
            self._device = None
            if self._hold is not None:
                self._hold.release()
                self._hold = None
        super().close()

    def _reconfigure_port(self) -> None:
        """Baud rate, parity and timeouts need no configuring on a simulated line."""

    def _settle(self) -> None:
        """Move replies whose time has come from in flight to arrived."""
        now = time.monotonic()
        while self._in_flight and self._in_flight[0][0] <= now:
            self._arrived += self._in_flight.popleft()[1]

    @property
    def in_waiting(self) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        with self._changed:
            self._settle()
            return len(self._arrived)

    @property
    def out_waiting(self) -> int:
        return 0

    def read(self, size: int = 1) -> bytes:
        """Up to `size` bytes: waits for them up to the port's timeout (None: forever, 0: not at all)."""
        if not self.is_open:
            raise PortNotOpenError()
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        data = bytearray()
        with self._changed:
            while True:
                self._settle()
                take = min(size - len(data), len(self._arrived))
                data += self._arrived[:take]
                del self._arrived[:take]
                now = time.monotonic()
                if len(data) >= size or (deadline is not None and now >= deadline):
                    return bytes(data)
                waits = [self._in_flight[0][0] - now] if self._in_flight else []
                waits += [deadline - now] if deadline is not None else []
                self._changed.wait(min(waits) if waits else None)

    def write(self, data: ReadableBuffer) -> int:
        """Hand the bytes to the emulator; its replies arrive reply_delay_s later, after earlier ones."""
        if not self.is_open or self._device is None:
            raise PortNotOpenError()
        sent = bytes(data)
        reply = self._device.receive(sent)
        if reply:
            with self._changed:
                arrives = time.monotonic() + self._device.reply_delay_s
                if self._in_flight:
                    arrives = max(arrives, self._in_flight[-1][0])
                self._in_flight.append((arrives, reply))
                self._changed.notify_all()
        return len(sent)

    def reset_input_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        with self._changed:
            self._settle()
            self._arrived.clear()

    def reset_output_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
