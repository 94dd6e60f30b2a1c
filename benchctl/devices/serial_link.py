"""One locked serial connection to a device that speaks a line protocol (a command line in, reply lines out).

Everything that makes serial drivers fragile lives here once, so drivers only say which command means what:
replies are framed by the exact line ending, input is flushed before every command so a stale reply is never
taken for the answer to the next one (and after a lost reply the line is drained until quiet), an echoed
command is consumed when the device echoes and reported when it echoes unexpectedly, and every failure is a
one-line DeviceError naming the device, the port and the command. Channels of one multi-channel unit share
one link; its lock keeps each command and its reply together when several threads use them.

Ports are opened with `serial.serial_for_url`, so device paths, `socket://`, `loop://` and the simulator's
`sim://` all work; tests can instead hand in any object with the few methods of `SerialPort`.
"""

from __future__ import annotations

import errno
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import Protocol, TypeVar

import serial

from benchctl.devices.errors import DeviceBusy, DeviceError, DeviceTimeout

SIM_HANDLERS = "benchctl.devices.sim"  # holds protocol_sim.py, pyserial's handler for sim:// URLs
MAX_REPLY_LINES = 64  # a multi-line reply longer than this means the framing is lost
MAX_LINE_BYTES = 4096  # a reply line longer than this means the framing is lost (or a flood: socket:// ports)
_BUSY = {errno.EBUSY, errno.EAGAIN, errno.EWOULDBLOCK}
T = TypeVar("T")


class SerialPort(Protocol):
    """The part of pyserial's port API a SerialLink uses (a test double needs only these)."""

    @property
    def in_waiting(self) -> int: ...

    def read(self, size: int = 1, /) -> bytes: ...

    def write(self, data: bytes, /) -> int | None: ...

    def flush(self) -> None: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


class ErrorReply(DeviceError):
    """The device answered a command with its error reply (the message carries the device's text)."""


def open_port(url: str, *, baudrate: int, timeout_s: float, name: str) -> SerialPort:
    """Open `url` (device path or pyserial URL, sim:// included) or raise a DeviceError that says why not."""
    if SIM_HANDLERS not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(SIM_HANDLERS)
    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s, exclusive=True)
    except serial.SerialException as exc:
        code = exc.errno if isinstance(exc.errno, int) else None
        if code in _BUSY:
            raise DeviceBusy(f"{name}: port {url} is busy (open in another program): {exc}") from None
        if code == errno.ENOENT:
            raise DeviceError(f"{name}: port {url} not found (is the device plugged in and powered?)") from None
        if code == errno.EACCES:
            raise DeviceError(f"{name}: no permission to open port {url} (on Linux: join the dialout group)") from None
        raise DeviceError(f"{name}: cannot open port {url}: {exc}") from None
    except ValueError as exc:  # unknown URL scheme, bad baud rate
        raise DeviceError(f"{name}: cannot open port {url}: {exc}") from None


class SerialLink:
    """A command/reply connection over one serial port; see the module docstring for what it guarantees."""

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = 115200,
        timeout_s: float = 1.0,
        line_ending: str = "\r\n",
        write_delay_s: float = 0.0,
        echo: bool = False,
        error_prefix: str | None = None,
        name: str = "device",
        port: SerialPort | None = None,
    ) -> None:
        """Open `url`, or use `port` when given (tests inject a scripted port that way; `url` then only names it).

        `error_prefix`: a reply line starting with it is the device refusing the command (ErrorReply).
        `write_delay_s`: pause after each write, for USB-serial adapters that drop bytes sent too soon.
        """
        if not line_ending:
            raise DeviceError(f"{name} ({url}): the line ending must not be empty")
        self.url = url
        self.name = name
        self.timeout_s = timeout_s
        self.line_ending = line_ending
        self.write_delay_s = write_delay_s
        self.echo = echo
        self.error_prefix = error_prefix
        self._terminator = line_ending.encode("ascii")
        self._rx = bytearray()
        self._lock = threading.RLock()
        self._unsettled = False  # an exchange broke off: a late reply may still arrive
        if port is None:
            port = open_port(url, baudrate=baudrate, timeout_s=timeout_s, name=name)
        self._port: SerialPort | None = port

    @property
    def where(self) -> str:
        """The device's name and port, e.g. "laser red (/dev/ttyUSB0)": how every message names this link."""
        return f"{self.name} ({self.url})"

    def query(self, command: str) -> str:
        """Send `command` and return its one reply line (without the line ending)."""
        return self._exchange(command, lambda: self._reply_line(command))

    def query_lines(self, command: str, until: str) -> list[str]:
        """Send `command` and return its reply lines up to (not including) the line equal to `until`."""
        def read() -> list[str]:
            lines: list[str] = []
            while (line := self._reply_line(command)) != until:
                lines.append(line)
                if len(lines) > MAX_REPLY_LINES:
                    raise DeviceError(f"{self.where}: no {until!r} after {MAX_REPLY_LINES} reply lines to {command!r}")
            return lines
        return self._exchange(command, read)

    def query_prompted(self, command: str, prompt: str) -> list[str]:
        """Send `command` and return its reply lines up to `prompt`, which a device that prompts for its next command
        sends (without a line ending) once it has answered: the exchange ends there, not at a timeout."""
        marker = prompt.encode("ascii")

        def read() -> list[str]:
            lines: list[str] = []
            while (line := self._next_line(command, marker)) is not None:
                lines.append(line)
                if len(lines) > MAX_REPLY_LINES:
                    raise DeviceError(f"{self.where}: no prompt {prompt!r} after {MAX_REPLY_LINES} reply lines to "
                                      f"{command!r}")
            return lines
        return self._exchange(command, read)

    def command(self, command: str, ok_reply: str = "OK") -> None:
        """Send a command that answers `ok_reply`; anything else (an error reply included) is a DeviceError."""
        def read() -> None:
            line = self._reply_line(command)
            if line != ok_reply:
                raise DeviceError(f"{self.where}: unexpected reply to {command!r}: {line!r} (expected {ok_reply!r})")
        self._exchange(command, read)

    def close(self) -> None:
        """Close the port (idempotent)."""
        with self._lock:
            port, self._port = self._port, None
            if port is not None:
                port.close()

    def __enter__(self) -> SerialLink:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- one exchange: resynchronise, write, read the reply -------------------------------------------------------

    def _exchange(self, command: str, read: Callable[[], T]) -> T:
        with self._lock:
            if self._port is None:
                raise DeviceError(f"{self.where}: cannot send {command!r}: the port is closed")
            try:
                self._send(command)
                result = read()
            except ErrorReply:
                raise  # the device answered in full: the line is in step
            except BaseException:
                self._unsettled = True
                raise
            return result

    def _send(self, command: str) -> None:
        """Flush what is waiting (draining first after a broken exchange), write the command, consume its echo."""
        try:
            data = (command + self.line_ending).encode("ascii")
        except UnicodeEncodeError:
            raise DeviceError(f"{self.where}: command {command!r} is not plain ASCII") from None
        port = self._port
        assert port is not None
        try:
            if self._unsettled:
                self._drain()
            port.reset_input_buffer()
            self._rx.clear()
            port.write(data)
            port.flush()
        except serial.SerialException as exc:
            raise DeviceError(f"{self.where}: connection lost sending {command!r}: {exc}") from None
        if self.write_delay_s:
            time.sleep(self.write_delay_s)
        if self.echo:
            line = self._line(command)
            if line != command:
                raise DeviceError(
                    f"{self.where}: expected the echo of {command!r}, got {line!r} (does the device echo?)"
                )

    def _drain(self) -> None:
        """Discard input until the line has been quiet for one timeout (bounded), so a late reply cannot be taken
        for the answer to the next command."""
        port = self._port
        assert port is not None
        give_up = time.monotonic() + 2 * self.timeout_s
        while port.read(max(1, port.in_waiting)) and time.monotonic() < give_up:
            pass
        self._unsettled = False

    def _reply_line(self, command: str) -> str:
        """The next reply line to `command`: an echo where none is expected and error replies are DeviceErrors."""
        line = self._line(command)
        if line == command and not self.echo:
            raise DeviceError(f"{self.where}: the device echoed {command!r}, but echo is not configured for it")
        if self.error_prefix and line.startswith(self.error_prefix):
            raise ErrorReply(f"{self.where}: {command!r} refused: {line}")
        return line

    def _line(self, command: str) -> str:
        """Read one line framed by the line ending; DeviceTimeout if nothing comes, DeviceError if garbled."""
        line = self._next_line(command, b"")
        assert line is not None  # no prompt to stop at
        return line

    def _next_line(self, command: str, prompt: bytes) -> str | None:
        """`_line`, or None (consumed) when what has arrived is `prompt` (when not empty) rather than a line."""
        port = self._port
        assert port is not None
        deadline = time.monotonic() + self.timeout_s
        while (end := self._rx.find(self._terminator)) < 0:
            if prompt and self._rx.startswith(prompt):
                del self._rx[:len(prompt)]
                return None
            try:
                chunk = port.read(max(1, port.in_waiting))
            except serial.SerialException as exc:
                raise DeviceError(
                    f"{self.where}: connection lost waiting for the reply to {command!r}: {exc}"
                ) from None
            self._rx += chunk
            if len(self._rx) > MAX_LINE_BYTES and self._rx.find(self._terminator) < 0:
                raise DeviceError(f"{self.where}: reply to {command!r} is over {MAX_LINE_BYTES} bytes without a "
                                  f"{self.line_ending!r} (wrong line ending, or not the expected device?)")
            if not chunk or time.monotonic() > deadline:
                if self._rx:
                    raise DeviceError(
                        f"{self.where}: garbled reply to {command!r}: {bytes(self._rx)!r} "
                        f"(no {self.line_ending!r} within {self.timeout_s:g} s)"
                    )
                raise DeviceTimeout(f"{self.where}: no reply to {command!r} within {self.timeout_s:g} s")
        raw = bytes(self._rx[:end])
        del self._rx[: end + len(self._terminator)]
        try:
            text: str | None = raw.decode("ascii")
        except UnicodeDecodeError:
            text = None
        if text is None or not text.isprintable():
            raise DeviceError(f"{self.where}: garbled reply to {command!r}: {raw!r} (wrong baud rate or noise?)")
        return text
