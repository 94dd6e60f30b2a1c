"""The console's laser panel: setpoints, emission, read-back and the dead-man switch, all through the Laser driver.

The driver keeps every safety rule (limits refused before anything is sent, every setting read back, emission
checked against interlock and faults, emission off at connect and at close); this module adds what a page that can
disappear needs: emission stays on only while a page shows it. Every message a page sends over its socket is a
heartbeat (it answers each state message and frame the server sends, and sends one every second besides); when no
heartbeat came for `deadman_s` (the tab closed, the network went, the browser hung, the console's own process
stopped answering) every channel is switched off. `all_off` is always allowed and tries every channel.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from benchctl.console.devices import Held
from benchctl.devices.errors import EmissionNotOff
from benchctl.devices.laser import Laser, open_laser
from benchctl.devices.laser.base import UNKNOWN_EMISSION
from benchctl.devices.power import format_power
from benchctl.errors import BadValueError, BenchctlError
from benchctl.profiles import Profile

DEADMAN_S = 3.0  # no heartbeat from any page for this long: emission off
MAX_DEADMAN_S = 300.0  # a dead-man that waits longer than minutes guards nothing
STALL_S = 0.5  # the watchdog woke this late: the process was stopped
STALL_GRACE_S = 1.0  # after a stall, time for the server to read what the page sent meanwhile


class LaserControl:
    """The profile's laser held by the console, with the channels it switched on and the dead-man timer."""

    def __init__(self, profile: Profile, say: Callable[[str], None], deadman_s: float = DEADMAN_S) -> None:
        self.profile = profile
        self.config = profile.section("laser")
        self.held: Held[Laser] = Held("laser", lambda: open_laser(self.config), self._shut)
        self.say = say
        if not 0 < deadman_s <= MAX_DEADMAN_S:
            raise BadValueError(f"the dead-man timeout must be above 0 and at most {MAX_DEADMAN_S:g} s, got "
                                f"{deadman_s:g} s")
        self.deadman_s = deadman_s
        self.emitting: set[str] = set()  # channels this console switched on and not off since
        self.unknown: str | None = None  # set when a switch-off could not be confirmed
        self._last_heartbeat = time.monotonic()
        self._stop = threading.Event()
        self._watch = threading.Thread(target=self._watchdog, name="console dead-man", daemon=True)

    # -- connection ------------------------------------------------------------------------------------------

    def connect(self) -> None:
        """Open the laser (emission off on every channel, read back) and say which channels were emitting."""
        if self.held.connect():
            with self.held.use() as laser:
                for line in laser.connect_report():
                    self.say(f"laser: {line}")
        if not self._watch.is_alive():
            self._watch.start()

    def close(self) -> None:
        """The dead-man stops and the laser is let go (`let_go`); never raises: `unknown` keeps why emission could
        not be confirmed off, for the console's last word."""
        self._stop.set()
        self.let_go()

    def let_go(self) -> bool:
        """Emission off on every channel, setpoints back and the laser closed (the driver's close, which closes the
        ports however it ends). True when emission is known to be off (confirmed now, or by an earlier let-go);
        False, with `unknown` saying why, when switching off could not be confirmed."""
        was_held = self.held.connected
        try:
            self.held.release()
        except Exception as exc:  # noqa: BLE001 - whatever went wrong on the way out, emission is not confirmed off
            self.unknown = str(exc) if UNKNOWN_EMISSION in str(exc) else f"{exc}; {UNKNOWN_EMISSION}"
            self.say(f"laser: letting go failed: {self.unknown}")
            return False
        finally:
            self.emitting.clear()
        if was_held:
            self.unknown = None
        return self.unknown is None

    def _shut(self, laser: Laser) -> None:
        """Let go of the laser as a run does: emission off, every setpoint back to the profile's (said), closed."""
        try:
            laser.all_off()
            for line in laser.restore_setpoints("the console"):
                self.say(f"laser: {line}")
        finally:
            laser.close()

    # -- commands ----------------------------------------------------------------------------------------------

    def set_power(self, channel: str, power: str) -> float:
        """The channel's setpoint (`power` as "20mW", "0.02W" or "5%" of its limit), read back (W). Above the
        profile's limit: SafetyError from the driver, nothing sent."""
        with self.held.use() as laser:
            watts = laser.set_power(channel, power)
        self.say(f"laser {channel}: setpoint {format_power(watts)} (read back)")
        return watts

    def set_emission(self, channel: str, on: bool) -> None:
        """Emission on or off, read back; on needs a page that sends heartbeats (the dead-man)."""
        with self.held.use() as laser:
            if on:
                self.heartbeat()  # the timer starts from the command that turned the light on
                laser.set_emission(channel, True)
                self.emitting.add(channel)
            else:
                self.emitting.discard(channel)
                self._switched_off(lambda: laser.set_emission(channel, False))
        self.say(f"laser {channel}: emission {'ON' if on else 'off'}")

    def all_off(self, why: str = "all off") -> None:
        """Emission off on every channel (each tried, read back); UNKNOWN said loudly when not confirmed."""
        self.emitting.clear()
        with self.held.use() as laser:
            self._switched_off(laser.all_off)
        self.say(f"laser: emission off on every channel ({why})")

    def _switched_off(self, action: Callable[[], None]) -> None:
        try:
            action()
            self.unknown = None
        except EmissionNotOff as exc:
            self.unknown = str(exc)
            self.say(f"laser: {exc}")
            raise

    # -- state ------------------------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """Per channel: limit, setpoint and measured power (mW), emission, interlock and faults, as the device
        reports them now; or why the laser cannot be read. `unknown` is set while emission may be on unseen."""
        base: dict[str, Any] = {"connected": self.held.connected, "error": self.held.error, "unknown": self.unknown,
                                "deadman_s": self.deadman_s, "channels": []}
        limits = {channel.name: channel.max_power_mw for channel in self.config.channels}
        if not self.held.connected:
            base["channels"] = [{"name": name, "limit_mw": limit} for name, limit in limits.items()]
            return base
        try:
            with self.held.use() as laser:
                statuses = [laser.status(name) for name in laser.channel_names]
        except BenchctlError as exc:
            base["error"] = str(exc)
            base["unknown"] = self.unknown or (f"{exc}; {UNKNOWN_EMISSION}" if self.emitting else None)
            return base
        base["channels"] = [{
            "name": s.name, "wavelength_nm": s.wavelength_nm, "limit_mw": limits[s.name],
            "setpoint_mw": round(s.setpoint_w * 1e3, 4),
            "measured_mw": None if s.measured_w is None else round(s.measured_w * 1e3, 4),
            "emission": s.emission, "interlock": s.interlock_ok, "faults": list(s.faults),
        } for s in statuses]
        return base

    # -- dead-man --------------------------------------------------------------------------------------------------

    def heartbeat(self) -> None:
        """A page is there (called for every message a page's socket sends)."""
        self._last_heartbeat = time.monotonic()

    def _watchdog(self) -> None:
        """Every `period`, emission off if no page has been heard from for `deadman_s`. When this thread itself did
        not run for a while (the whole process was stopped: a machine short of memory stalls every program, or
        SIGSTOP), what a page sent meanwhile may still wait unread in the socket: the server gets STALL_GRACE_S to
        read it before silence counts."""
        period = min(0.1, self.deadman_s / 4)
        due = time.monotonic() + period
        judge_from = 0.0
        while not self._stop.wait(period):
            now = time.monotonic()
            if now - due > STALL_S:
                judge_from = now + STALL_GRACE_S
            due = now + period
            silent = now - self._last_heartbeat
            if self.emitting and silent > self.deadman_s and now >= judge_from:
                try:
                    self.all_off(f"dead-man: no page for {silent:.1f} s")
                except BenchctlError as exc:
                    self.say(f"laser: dead-man switch-off failed: {exc}")
