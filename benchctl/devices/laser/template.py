"""The "template" driver: a multi-channel unit whose line protocol is written in the profile ([laser.protocol]).

Commands are format strings with {channel} (the channel's index), {mw} and {w} (the power in mW / W); power
replies are read in `power_unit`. Emission replies may be 1/0 or ON/OFF. The status reply is the OK reply when
all is well, contains "INTERLOCK" when the interlock is open, and is otherwise the fault's own text. Optional
commands that are missing make the matching readings unavailable (None) rather than guessed.
"""

from __future__ import annotations

from typing import Any

from benchctl.devices.laser.base import Laser
from benchctl.errors import BenchctlError
from benchctl.profiles import LaserChannel, LaserConfig


class TemplateLaser(Laser):
    """A laser unit driven by the command templates of the profile; its channels share one port."""

    def __init__(self, config: LaserConfig, **options: Any) -> None:
        super().__init__(config, **options)
        if config.protocol is None:
            raise BenchctlError("the template laser driver needs a [laser.protocol] section with its commands")
        self.protocol = config.protocol
        self.line_ending = self.protocol.line_ending
        self.ok_reply = self.protocol.ok_reply
        self.error_prefix = self.protocol.error_prefix or None
        self.echo = self.protocol.echo
        self._units_per_watt = 1e3 if self.protocol.power_unit == "mW" else 1.0
        for key in ("set_power", "get_power", "enable", "disable", "get_measured", "get_emission", "get_status"):
            self._render(key, config.channels[0], 0.0)  # a bad placeholder fails now, not mid-experiment

    def _render(self, key: str, channel: LaserChannel, watts: float = 0.0) -> str:
        template = getattr(self.protocol, key)
        try:
            return template.format(channel=channel.index, mw=watts * 1e3, w=watts) if template else ""
        except (KeyError, IndexError, ValueError) as exc:
            raise BenchctlError(
                f"laser.protocol.{key}: cannot fill in {template!r} ({exc!r}); "
                "placeholders are {channel}, {mw}, {w}"
            ) from None

    def _identify(self, channel: LaserChannel) -> str:
        if not self.protocol.identify:
            return f"template laser on {self.config.port_of(channel)} (no identify command in [laser.protocol])"
        return self._query(channel, self.protocol.identify)

    def _write_power(self, channel: LaserChannel, watts: float) -> None:
        self._command(channel, self._render("set_power", channel, watts))

    def _read_setpoint(self, channel: LaserChannel) -> float:
        return self._query_number(channel, self._render("get_power", channel)) / self._units_per_watt

    def _read_measured(self, channel: LaserChannel) -> float | None:
        if not self.protocol.get_measured:
            return None
        return self._query_number(channel, self._render("get_measured", channel)) / self._units_per_watt

    def _write_emission(self, channel: LaserChannel, on: bool) -> None:
        self._command(channel, self._render("enable" if on else "disable", channel))

    def _read_emission(self, channel: LaserChannel) -> bool | None:
        if not self.protocol.get_emission:
            return None
        return self._query_flag(channel, self._render("get_emission", channel))

    def _read_health(self, channel: LaserChannel) -> tuple[bool | None, tuple[str, ...]]:
        if not self.protocol.get_status:
            return None, ()
        reply = self._query(channel, self._render("get_status", channel))
        if reply == self.ok_reply:
            return True, ()
        if "INTERLOCK" in reply.upper():
            return False, ()
        return None, (reply,)
