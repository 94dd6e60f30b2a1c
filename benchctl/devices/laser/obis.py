"""The "obis" driver: Coherent OBIS heads (115200, CR LF, handshaking on: every reply is followed by `OK`,
errors are `ERR-<code>`).

One head per port by default; when channels share a port (a multi-head box) every command names its head
after the first keyword (`SOURce2:AM:STATe ON`), using the channel's index. Commands: at connect
`SYSTem:AUTostart OFF`, `SYSTem:CDRH OFF` (no 5 s emission delay) and `SOURce:POWer:LIMit:HIGH?` (the head's
max power; setpoints above it are refused before sending); `SOURce:POWer:LEVel:IMMediate:AMPLitude <W>` and
`...?` (setpoint), `SOURce:POWer:LEVel?` (measured), `SOURce:AM:STATe ON|OFF` and `?` (emission),
`SYSTem:FAULt?` (fault bits), `SYSTem:LOCK?` (interlock: ON = closed) and `*IDN?` (identity).
"""

from __future__ import annotations

from benchctl.devices.errors import DeviceError
from benchctl.devices.laser.base import Laser
from benchctl.profiles import LaserChannel

FAULT_BITS = {
    0x1: "base plate temperature out of range",
    0x2: "diode temperature out of range",
    0x4: "internal temperature out of range",
    0x8: "no power to the laser diode",
    0x20: "diode over current",
    0x200: "warm-up time limit exceeded",
    0x2000: "cannot emit at the set power",
    0x8000: "irrecoverable system failure",
}


class ObisLaser(Laser):
    """Coherent OBIS heads, one per port or several in a box on one port (addressed by channel index)."""

    error_prefix = "ERR"

    def _addressed(self, channel: LaserChannel, command: str) -> str:
        """`command` for `channel`'s head: the head number goes after the first keyword on a shared port."""
        if command.startswith("*") or not self._shares_port(channel):
            return command
        first, sep, rest = command.partition(":")
        return f"{first}{channel.index}{sep}{rest}"

    def _query(self, channel: LaserChannel, command: str) -> str:
        """A query's one reply line (the handshake's OK line consumed)."""
        command = self._addressed(channel, command)
        lines = self._link(channel).query_lines(command, until=self.ok_reply)
        if len(lines) != 1:
            raise DeviceError(f"{self._link(channel).where}: expected one reply line to {command!r}, got {lines!r}")
        return lines[0]

    def _command(self, channel: LaserChannel, command: str) -> None:
        super()._command(channel, self._addressed(channel, command))

    def _prepare(self, channel: LaserChannel) -> None:
        self._command(channel, "SYSTem:AUTostart OFF")
        self._command(channel, "SYSTem:CDRH OFF")

    def _read_limit_w(self, channel: LaserChannel) -> float | None:
        return self._query_number(channel, "SOURce:POWer:LIMit:HIGH?")

    def _identify(self, channel: LaserChannel) -> str:
        return self._query(channel, "*IDN?")

    def _write_power(self, channel: LaserChannel, watts: float) -> None:
        self._command(channel, f"SOURce:POWer:LEVel:IMMediate:AMPLitude {watts:.6f}")

    def _read_setpoint(self, channel: LaserChannel) -> float:
        return self._query_number(channel, "SOURce:POWer:LEVel:IMMediate:AMPLitude?")

    def _read_measured(self, channel: LaserChannel) -> float | None:
        return self._query_number(channel, "SOURce:POWer:LEVel?")

    def _write_emission(self, channel: LaserChannel, on: bool) -> None:
        self._command(channel, f"SOURce:AM:STATe {'ON' if on else 'OFF'}")

    def _read_emission(self, channel: LaserChannel) -> bool | None:
        return self._query_flag(channel, "SOURce:AM:STATe?")

    def _read_health(self, channel: LaserChannel) -> tuple[bool | None, tuple[str, ...]]:
        interlock_closed = self._query_flag(channel, "SYSTem:LOCK?")
        reply = self._query(channel, "SYSTem:FAULt?")
        try:
            code = int(reply, 16) if reply.lower().startswith("0x") else int(reply)
        except ValueError:
            where = self._link(channel).where
            raise DeviceError(f"{where}: expected a fault code from 'SYSTem:FAULt?', got {reply!r}") from None
        bits = [1 << i for i in range(32) if code >> i & 1]
        return interlock_closed, tuple(FAULT_BITS.get(bit, f"fault bit 0x{bit:X}") for bit in bits)
