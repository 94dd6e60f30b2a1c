"""The "sapphire" driver: Coherent Sapphire heads, one serial port per channel (19200 8N1, CR LF: set
laser.baudrate = 19200).

Out of the box a head echoes what it receives and prompts for the next command with `Sapphire:0-> ` (no line
ending). On every connection benchctl turns the prompt on (`>=1`) and echo off (`E=0`), taking either echo state as
it finds it; from then on the head still sends back the line ending of each command, so a reply is an empty line,
then its answer (a query's value; a setting answers only to refuse it or with a note), then the prompt, which ends the
exchange without waiting for a timeout. Powers are in mW: `P=<mW>`, `?SP` (setpoint), `?P` (output), `?MAXLP` (the
head's maximum; setpoints above it are refused before sending). Emission is the light servo: `L=1` / `L=0`, `?L`.
Health: `?K` (key switch: 0 standby, 1 on) and `?FF` (fault bits: bit 0 the external interlock, bit 13 "laser
ready", which is no fault). Identity: `?HID` (head id). A head emits as soon as its key is turned on: connecting
switches it off like every other (there is no autostart setting to clear).
"""

from __future__ import annotations

from typing import Any

from benchctl.devices.errors import DeviceError
from benchctl.devices.laser.base import Laser
from benchctl.profiles import LaserChannel, LaserConfig

PROMPT = "Sapphire:0-> "
INTERLOCK_BIT = 0
READY_BIT = 13
FAULT_BITS = {
    1: "diode temperature fault (TEC and light servo off)",
    2: "base plate temperature fault (TEC and light servo off)",
    3: "controller temperature fault (TEC and light servo off)",
    4: "diode current fault",
    5: "analog interface fault",
    6: "base plate temperature fault (light servo off)",
    7: "diode temperature fault (light servo off)",
    8: "waiting for the TEC servo to reach its temperature",
    9: "head EEPROM fault",
    10: "controller EEPROM fault",
    11: "EEPOT1 fault",
    12: "EEPOT2 fault",
}


class SapphireLaser(Laser):
    """Coherent Sapphire heads, one per channel, each on its own port (channel.port, or laser.port for one)."""

    one_head_per_port = True

    def __init__(self, config: LaserConfig, **options: Any) -> None:
        super().__init__(config, **options)
        self._framed: set[str] = set()  # ports whose head has the prompt on and echo off

    def _lines(self, channel: LaserChannel, command: str) -> list[str]:
        """The answer lines to `command` (the returned line ending and the prompt taken off)."""
        link = self._link(channel)
        if link.url not in self._framed:
            for setting in (">=1", "E=0"):  # either echo state: the setting itself, or its line ending, comes back
                got = link.query_prompted(setting, PROMPT)
                if not set(got) <= {"", setting}:
                    raise DeviceError(f"{link.where}: unexpected reply to {setting!r}: {got!r} (is it a Sapphire, at "
                                      f"laser.baudrate 19200?)")
            self._framed.add(link.url)
        lines = link.query_prompted(command, PROMPT)
        if not lines or lines[0] != "":
            raise DeviceError(f"{link.where}: reply to {command!r} does not start with the returned line ending: "
                              f"{lines!r}")
        return lines[1:]

    def _query(self, channel: LaserChannel, command: str) -> str:
        lines = self._lines(channel, command)
        if len(lines) != 1:
            raise DeviceError(f"{self._link(channel).where}: expected one reply line to {command!r}, got {lines!r}")
        return lines[0]

    def _command(self, channel: LaserChannel, command: str) -> None:
        refused = [line for line in self._lines(channel, command) if not line.startswith("Note:")]
        if refused:
            raise DeviceError(f"{self._link(channel).where}: {command!r} refused: {'; '.join(refused)}")

    def _read_limit_w(self, channel: LaserChannel) -> float | None:
        return self._query_number(channel, "?MAXLP") * 1e-3

    def _identify(self, channel: LaserChannel) -> str:
        return f"Coherent Sapphire, head {self._query(channel, '?HID')}"

    def _write_power(self, channel: LaserChannel, watts: float) -> None:
        self._command(channel, f"P={watts * 1e3:.3f}")

    def _read_setpoint(self, channel: LaserChannel) -> float:
        return self._query_number(channel, "?SP") * 1e-3

    def _read_measured(self, channel: LaserChannel) -> float | None:
        return self._query_number(channel, "?P") * 1e-3

    def _write_emission(self, channel: LaserChannel, on: bool) -> None:
        self._command(channel, "L=1" if on else "L=0")

    def _read_emission(self, channel: LaserChannel) -> bool | None:
        return self._query_flag(channel, "?L")

    def _read_health(self, channel: LaserChannel) -> tuple[bool | None, tuple[str, ...]]:
        key_on = self._query_flag(channel, "?K")
        bits = int(self._query_number(channel, "?FF"))
        faults = [text for bit, text in FAULT_BITS.items() if bits >> bit & 1]
        faults += [f"fault bit {bit}" for bit in range(14, 16) if bits >> bit & 1]
        if not key_on:
            faults.insert(0, "key switch at standby")
        return not bits >> INTERLOCK_BIT & 1, tuple(faults)
