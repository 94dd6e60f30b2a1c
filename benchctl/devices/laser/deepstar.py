"""The "deepstar" driver: Omicron Deepstar (LuxX) heads, one serial port per channel (9600 8N1: set
laser.baudrate = 9600).

The head reads commands of a fixed length: each is padded with spaces to 14 characters and ends with CR LF (16
bytes); replies end with CR LF. It is in one of three states: S0 (an error, or the interlock open), S1 (standby), S2
(laser on). Commands: `S?` (the state), `LON` (S1 -> S2: `LONOK`; `INT` when interlocked), `LF` (S2 -> S1: `LOFFOK`;
`UK` when it was not on), `L2` (in S2: Deepstar mode, `>`), `IPO` (internal peak power on), `PP<3 hex digits>` and
`PP?` (the power setpoint in steps of the head's maximum / 0xFFF), `P?` (the output power, 0xCCC being the maximum),
`STAT0` (model code: wavelength and maximum power in mW, its setpoints above it are refused before sending) and
`STAT2` (firmware and serial numbers). Emission counts as on whenever the head is in S2, whatever its mode and
modulation: the reading that never says off for a head that may emit. Switching on is LON, L2, IPO; off is LF.
"""

from __future__ import annotations

from typing import Any

from benchctl.devices.errors import DeviceError, SafetyError
from benchctl.devices.laser.base import Laser
from benchctl.profiles import LaserChannel, LaserConfig

WIDTH = 14  # characters of a command before its line ending
SETPOINT_FULL = 0xFFF  # PP: the head's maximum power
OUTPUT_FULL = 0xCCC  # P?: the head's maximum power (0xFFF is 120 %)


class DeepstarLaser(Laser):
    """Omicron Deepstar heads, one per channel, each on its own port (channel.port, or laser.port for one)."""

    one_head_per_port = True

    def __init__(self, config: LaserConfig, **options: Any) -> None:
        super().__init__(config, **options)
        self._model: dict[str, tuple[str, float]] = {}  # port -> (wavelength nm, maximum W) from STAT0

    def _query(self, channel: LaserChannel, command: str) -> str:
        return self._link(channel).query(command.ljust(WIDTH))

    def _expect(self, channel: LaserChannel, command: str, *accepted: str) -> str:
        """Send `command`; its reply, which must be one of `accepted` (DeviceError naming it otherwise)."""
        reply = self._query(channel, command)
        if reply not in accepted:
            raise DeviceError(f"{self._link(channel).where}: {command!r} refused: {reply!r} (expected "
                              f"{' or '.join(map(repr, accepted))})")
        return reply

    def _head(self, channel: LaserChannel) -> tuple[str, float]:
        """(wavelength, maximum power in W) from the model code, asked once per connection."""
        url = self.config.port_of(channel)
        if url not in self._model:
            reply = self._query(channel, "STAT0")
            numbers = [token for token in reply.split() if token.isdigit()]
            if not reply.startswith("MC") or len(numbers) < 2:
                raise DeviceError(f"{self._link(channel).where}: expected a model code 'MC <nm> <mW> ...' in reply to "
                                  f"'STAT0', got {reply!r}")
            self._model[url] = (numbers[0], int(numbers[1]) * 1e-3)
        return self._model[url]

    def _hex(self, channel: LaserChannel, command: str, prefix: str, digits: int) -> int:
        reply = self._query(channel, command)
        value = reply[len(prefix):]
        if not reply.startswith(prefix) or len(value) != digits or any(c not in "0123456789ABCDEFabcdef"
                                                                       for c in value):
            raise DeviceError(f"{self._link(channel).where}: expected {prefix} and {digits} hex digits in reply to "
                              f"{command!r}, got {reply!r}")
        return int(value, 16)

    def _read_limit_w(self, channel: LaserChannel) -> float | None:
        return self._head(channel)[1]

    def _setpoint_step_w(self, channel: LaserChannel) -> float:
        return self._head(channel)[1] / SETPOINT_FULL

    def _identify(self, channel: LaserChannel) -> str:
        wavelength, maximum = self._head(channel)
        serials = [token[3:] for token in self._query(channel, "STAT2").split() if token.startswith("SNP")]
        return f"Omicron Deepstar {wavelength} nm {maximum * 1e3:g} mW, head serial {serials[0] if serials else '?'}"

    def _write_power(self, channel: LaserChannel, watts: float) -> None:
        level = round(watts / self._head(channel)[1] * SETPOINT_FULL)
        command = f"PP{level:03X}"
        self._expect(channel, command, command)

    def _read_setpoint(self, channel: LaserChannel) -> float:
        return self._hex(channel, "PP?", "PP", 3) / SETPOINT_FULL * self._head(channel)[1]

    def _read_measured(self, channel: LaserChannel) -> float | None:
        return self._hex(channel, "P?", "P", 4) / OUTPUT_FULL * self._head(channel)[1]

    def _write_emission(self, channel: LaserChannel, on: bool) -> None:
        if not on:
            self._expect(channel, "LF", "LOFFOK", "UK")  # UK: it was not on
            return
        if self._expect(channel, "LON", "LONOK", "INT") == "INT":
            raise SafetyError(f"{self._where(channel)}: interlock open (LON answered INT): emission not enabled")
        self._expect(channel, "L2", ">")
        self._expect(channel, "IPO", "IPO")

    def _state(self, channel: LaserChannel) -> str:
        return self._expect(channel, "S?", "S0", "S1", "S2")

    def _read_emission(self, channel: LaserChannel) -> bool | None:
        return self._state(channel) == "S2"

    def _read_health(self, channel: LaserChannel) -> tuple[bool | None, tuple[str, ...]]:
        if self._state(channel) == "S0":
            return None, ("error or interlock open (state S0)",)
        return None, ()
