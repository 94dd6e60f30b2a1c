"""The "cobolt" driver: Cobolt single-wavelength heads, one serial port per channel (115200 8N1, CR LF).

Commands: `@cobas 0` (autostart off, at connect), `p <W>` / `p?` (setpoint), `pa?` (measured, W), `l1` / `l0` /
`l?` (emission), `f?` (fault code: 0 none, 1 temperature, 3 interlock open, 4 constant-power fault), `ilk?`
(0 interlock closed, 1 open), `gmlp?` (the head's max power, mW; setpoints above it are refused before sending)
and `gsn?` (serial number, the identity). Settings answer `OK`; bad commands `Syntax error: ...`.
"""

from __future__ import annotations

from typing import Any

from benchctl.devices.laser.base import Laser
from benchctl.errors import BenchctlError
from benchctl.profiles import LaserChannel, LaserConfig

FAULT_CODES = {1: "temperature error", 3: "interlock open", 4: "constant-power fault"}
INTERLOCK_FAULT = 3


class CoboltLaser(Laser):
    """Cobolt heads, one per channel, each on its own port (channel.port, or laser.port for a single channel)."""

    error_prefix = "Syntax error"

    def __init__(self, config: LaserConfig, **options: Any) -> None:
        super().__init__(config, **options)
        for port, channels in self._ports.items():
            if len(channels) > 1:
                names = ", ".join(ch.name for ch in channels)
                raise BenchctlError(
                    f"cobolt laser: channels {names} share port {port}, but a Cobolt head has one wavelength: "
                    "give each channel its own port"
                )

    def _prepare(self, channel: LaserChannel) -> None:
        self._command(channel, "@cobas 0")

    def _read_limit_w(self, channel: LaserChannel) -> float | None:
        return self._query_number(channel, "gmlp?") * 1e-3

    def _identify(self, channel: LaserChannel) -> str:
        return f"Cobolt laser, serial number {self._query(channel, 'gsn?')}"

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
