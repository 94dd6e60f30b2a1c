"""The "cobolt" driver: Cobolt single-wavelength heads, one serial port per channel (115200 8N1, CR LF).

Commands: `@cobas 0` (autostart off, at connect), `p <W>` / `p?` (setpoint), `pa?` (measured, W), `l1` / `l0` /
`l?` (emission), `f?` (fault code: 0 none, 1 temperature, 3 interlock open, 4 constant-power fault), `ilk?`
(0 interlock closed, 1 open), `gmlp?` (the head's max power, mW; setpoints above it are refused before sending)
and the serial number, the identity: `sn?` (what python-microscope asks, and its mock of a Cobolt Jive answers),
else `gsn?` where the firmware refuses `sn?` (Cobolt firmware families differ). Settings answer `OK`; bad commands
`Syntax error: ...`.
"""

from __future__ import annotations

from benchctl.devices.laser.base import Laser
from benchctl.devices.serial_link import ErrorReply
from benchctl.profiles import LaserChannel

FAULT_CODES = {1: "temperature error", 3: "interlock open", 4: "constant-power fault"}
INTERLOCK_FAULT = 3


class CoboltLaser(Laser):
    """Cobolt heads, one per channel, each on its own port (channel.port, or laser.port for a single channel)."""

    error_prefix = "Syntax error"
    one_head_per_port = True

    def _prepare(self, channel: LaserChannel) -> None:
        self._command(channel, "@cobas 0")

    def _read_limit_w(self, channel: LaserChannel) -> float | None:
        return self._query_number(channel, "gmlp?") * 1e-3

    def _identify(self, channel: LaserChannel) -> str:
        try:
            serial = self._query(channel, "sn?")
        except ErrorReply:  # a firmware family that only knows gsn?
            serial = self._query(channel, "gsn?")
        return f"Cobolt laser, serial number {serial}"

    def _write_power(self, channel: LaserChannel, watts: float) -> None:
        self._command(channel, f"p {watts:.6f}")

    def _read_setpoint(self, channel: LaserChannel) -> float:
        return self._query_number(channel, "p?")

    def _read_measured(self, channel: LaserChannel) -> float | None:
        return self._query_number(channel, "pa?")

    def _write_emission(self, channel: LaserChannel, on: bool) -> None:
        self._command(channel, "l1" if on else "l0")

    def _read_emission(self, channel: LaserChannel) -> bool | None:
        return self._query_flag(channel, "l?")

    def _read_health(self, channel: LaserChannel) -> tuple[bool | None, tuple[str, ...]]:
        interlock_open = self._query_flag(channel, "ilk?")
        code = int(self._query_number(channel, "f?"))
        faults = () if code in (0, INTERLOCK_FAULT) else (f"{FAULT_CODES.get(code, 'unknown fault')} (f? = {code})",)
        return not interlock_open and code != INTERLOCK_FAULT, faults
