"""Expected-protocol testing: a scripted stand-in for a serial port that asserts the exact bytes a driver sends.

    pairs = [(b"l0\r\n", b"OK\r\n"), (b"l?\r\n", b"0\r\n")]
    with ExpectedProtocol(pairs) as port:
        link = SerialLink("script://cobolt", port=port)      # or Laser(config, port_factory=...)
        ...
    # leaving the block checks that every pair was used

The port fails (AssertionError) on any write that is not the next expected command, on a read when no reply is
pending, when the driver flushes reply bytes it never read (framing out of step), and at the end on pairs never
used. Failures are also recorded, so a driver that swallows the AssertionError still fails check(). A reply of
`None`, or wrapped in `Stalls`, means the device then goes quiet: reads return b"" (a timeout) until the next
command.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from types import TracebackType


class Stalls(bytes):
    """A reply after which the device stays silent: reads past it time out instead of failing the test."""


class ExpectedProtocol:
    """A fake serial port replaying (sent bytes, reply bytes) pairs; see the module docstring."""

    def __init__(self, pairs: Iterable[tuple[bytes, bytes | None]], name: str = "port") -> None:
        self.name = name
        self._pairs: deque[tuple[bytes, bytes | None]] = deque(pairs)
        self._written = bytearray()
        self._pending = bytearray()
        self._silent = False
        self.failures: list[str] = []
        self.closed = False

    def _fail(self, message: str) -> AssertionError:
        self.failures.append(f"{self.name}: {message}")
        return AssertionError(self.failures[-1])

    # -- the SerialPort interface --------------------------------------------------------------------------------

    @property
    def in_waiting(self) -> int:
        return len(self._pending)

    def write(self, data: bytes) -> int:
        self._written += data
        written = bytes(self._written)
        if not self._pairs:
            raise self._fail(f"unexpected write {written!r}: no more exchanges expected")
        sent, reply = self._pairs[0]
        if not sent.startswith(written):
            raise self._fail(f"unexpected write {written!r}, expected {sent!r}")
        if written == sent:
            self._pairs.popleft()
            self._written.clear()
            self._pending = bytearray(reply or b"")
            self._silent = reply is None or isinstance(reply, Stalls)
        return len(data)

    def read(self, size: int = 1) -> bytes:
        if not self._pending:
            if self._silent:
                return b""
            raise self._fail("read with no reply pending")
        data = bytes(self._pending[:size])
        del self._pending[:size]
        return data

    def flush(self) -> None:
        """Nothing to flush: writes are matched as they come."""

    def reset_input_buffer(self) -> None:
        if self._pending and not self._silent:
            raise self._fail(f"unread reply bytes {bytes(self._pending)!r} discarded: reply framing out of step")
        self._pending.clear()

    def close(self) -> None:
        self.closed = True

    # -- checking ----------------------------------------------------------------------------------------------

    def check(self) -> None:
        """Fail on any recorded failure, on expected exchanges that never happened, or on an unread reply."""
        if self.failures:
            raise AssertionError(self.failures[0])
        if self._pairs:
            left = len(self._pairs)
            raise AssertionError(f"{self.name}: {left} expected exchange(s) never happened, next {self._pairs[0]!r}")
        if self._pending and not self._silent:
            raise AssertionError(f"{self.name}: reply {bytes(self._pending)!r} was never read")

    def __enter__(self) -> ExpectedProtocol:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.check()
