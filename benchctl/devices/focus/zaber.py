"""The `zaber` focus driver: the camera on a Zaber motorised linear stage, focused by moving it along the optical axis,
over Zaber's ASCII protocol (Zaber's "ASCII Protocol Manual"; one line per command and per reply):

    open:    /<d> <a>            status: the warning flag WR (no reference position) means the counter is not a
                                 position yet; otherwise `get pos` is (the controller remembers it while powered)
             /<d> 0 get system.serial, get version, /<d> <a> get limit.max
    move:    /<d> <a> move rel N  -> @<d> <a> OK BUSY -- 0; then the empty command until IDLE; get pos
    home:    /<d> <a> home        -> ... until IDLE (the home sensor; clears WR)
    close:   nothing: the stage holds its position unpowered-safe

A reply is `@<device> <axis> <OK|RJ> <IDLE|BUSY> <warning> <data>`: RJ is a refusal (BADDATA: beyond the travel,
BADCOMMAND), and a move that ends with the stall warning FS (or FQ, an encoder fault) is an error, since the counter
then no longer says where the camera is. The counter counts microsteps (`microstep_um` each); the stage's screw has
backlash the counter cannot see, which the focus calibration measures.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from benchctl.devices.errors import DeviceError, DeviceTimeout
from benchctl.devices.focus.base import Focus
from benchctl.devices.lock import DeviceLock
from benchctl.devices.safety import wait
from benchctl.devices.serial_link import SerialLink
from benchctl.profiles import FocusConfig, Profile

POLL_S = 0.02
FAULT_WARNINGS = {"FS": "the carriage stalled (something blocks it, or the load is too heavy)",
                  "FQ": "the encoder reports an error", "FD": "the driver is disabled (over-temperature?)"}


@dataclass(frozen=True)
class Reply:
    """One reply line, split into its fields."""

    device: int
    axis: int
    flag: str
    status: str
    warning: str
    data: str


def parse_reply(line: str) -> Reply | None:
    """The fields of a reply line `@01 1 OK IDLE -- 0`; None if the line is not one."""
    parts = line.split(" ", 5)
    if len(parts) < 6 or not parts[0].startswith("@") or not parts[0][1:].isdigit() or not parts[1].isdigit():
        return None
    return Reply(int(parts[0][1:]), int(parts[1]), parts[2], parts[3], parts[4], parts[5])


class ZaberFocus(Focus):
    """A Zaber stage carrying the camera; see the module docstring for the exact commands."""

    driver = "zaber"
    unit = "microstep"
    counts_steps = True

    def __init__(self, config: FocusConfig, link: SerialLink | None = None) -> None:
        super().__init__(config)
        self._given_link = link
        self._link: SerialLink | None = None
        self._info: dict[str, str] = {}
        self.limit_max: int | None = None

    @classmethod
    def for_profile(cls, profile: Profile) -> ZaberFocus:
        """The stage on the profile's port; on a sim:// port the simulated bench's stage, with the profile's hidden
        mechanics ([sim.focus])."""
        config = profile.section("focus")
        if config.port and config.port.startswith("sim://"):
            from benchctl.devices.sim.focus_mechanics import bind

            bind(profile.sim.focus)
        return cls(config)

    @property
    def travel(self) -> int | None:
        return self.limit_max

    def _device_lock(self) -> DeviceLock:
        return DeviceLock(f"focus:{self.config.port}", f"focus stage ({self.config.port})")

    def _open(self) -> None:
        port = self.config.port
        assert port is not None  # profiles check it
        self._link = self._given_link or SerialLink(port, baudrate=self.config.baudrate,
                                                    timeout_s=self.config.timeout_s, name="focus stage")
        try:
            status = self._ask("")
            self._info = {"serial": self._ask("get system.serial", axis=0).data,
                          "firmware": self._ask("get version", axis=0).data}
            self.limit_max = int(self._ask("get limit.max").data)
            self._position = None if status.warning == "WR" else int(self._ask("get pos").data)
        except BaseException:
            self._shutdown()
            raise

    def _close(self) -> None:
        self._shutdown()

    def _shutdown(self) -> None:
        if self._link is not None:
            self._link.close()
        self._link = None

    def _identity(self) -> dict[str, str]:
        travel = "unknown" if self.limit_max is None else f"{self.limit_max * self.config.microstep_um / 1000:g} mm"
        return {"manufacturer": "Zaber", **self._info, "travel": travel,
                "address": f"device {self.config.device} axis {self.config.axis}"}

    # -- commands -----------------------------------------------------------------------------------------------

    def _ask(self, command: str, axis: int | None = None) -> Reply:
        """Send `/<device> <axis> <command>` and return its reply; a refusal or a garbled reply is a DeviceError."""
        if self._link is None:
            raise DeviceError("focus stage is not connected")
        axis = self.config.axis if axis is None else axis
        text = f"/{self.config.device} {axis} {command}".rstrip()
        line = self._link.query(text)
        reply = parse_reply(line)
        if reply is None or reply.device != self.config.device or reply.axis != axis:
            raise DeviceError(f"{self._link.where}: unexpected reply to {text!r}: {line!r}")
        if reply.flag == "RJ":
            why = {"BADDATA": "beyond the stage's travel or not a valid number",
                   "BADCOMMAND": "a command this stage does not know"}.get(reply.data, reply.data)
            raise DeviceError(f"{self._link.where}: {text!r} refused ({reply.data}: {why})")
        if reply.flag != "OK":
            raise DeviceError(f"{self._link.where}: unexpected reply to {text!r}: {line!r}")
        return reply

    def _wait_idle(self, what: str) -> Reply:
        """Poll the status until the axis is IDLE; its warning checked for faults."""
        deadline = time.monotonic() + self.config.move_timeout_s
        while (reply := self._ask("")).status == "BUSY":
            if time.monotonic() > deadline:
                raise DeviceTimeout(f"focus stage ({self.config.port}): still moving {self.config.move_timeout_s:g} s "
                                    f"after {what}")
            wait(POLL_S)
        if reply.warning in FAULT_WARNINGS:
            raise DeviceError(f"focus stage ({self.config.port}): {what} ended with warning {reply.warning}: "
                              f"{FAULT_WARNINGS[reply.warning]}; its position is no longer known: free it, then "
                              f"`benchctl focus home`")
        return reply

    def _drive(self, steps: int) -> int | None:
        if self._position is None:
            raise DeviceError(f"focus stage ({self.config.port}) has no reference position (warning WR): home it "
                              f"first (`benchctl focus home`)")
        self._ask(f"move rel {steps}")
        self._wait_idle(f"move rel {steps}")
        return self._reported()

    def _home(self) -> None:
        self._ask("home")
        self._wait_idle("home")

    def _reported(self) -> int | None:
        return int(self._ask("get pos").data)

    def ground_truth(self) -> dict[str, float] | None:
        """The simulated stage's carriage (one mechanism step per microstep)."""
        if not (self.config.port or "").startswith("sim://"):
            return None
        from benchctl.devices.sim.focus_mechanics import Mechanism

        mechanism = Mechanism()
        return {"true_steps": mechanism.true_steps, "backlash_steps": mechanism.config.backlash_steps}
