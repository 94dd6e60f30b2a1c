"""A byte-level emulator of a Zaber motorised linear stage speaking Zaber's ASCII protocol, carrying the camera of the
simulated bench: the stage's travel moves the camera's focus plane (benchctl.devices.sim.focus_mechanics).

    sim://<name>?dialect=zaber&fault=a,b&speed=200000&reply_delay_s=0

Commands `/<device> <axis> <command> [data]` end with CR LF (a bare LF is accepted too); every reply is one line
`@<device, 2 digits> <axis> <OK|RJ> <IDLE|BUSY> <warning flag or --> <data>` ending CR LF. Implemented: the empty
command (status), `home`, `move abs N`, `move rel N`, `stop`, `get pos`, `get limit.min`, `get limit.max`,
`get system.serial`, `get version`, `warnings` (data: the count, then the flags), `warnings clear`. A move beyond the
travel is answered `RJ IDLE -- BADDATA`, an unknown command `RJ ... BADCOMMAND`; a message for another device
number gets no reply (nothing else is on the chain). The stage has no reference after power-on (`WR`) until it is
homed. A move keeps the axis BUSY for its distance / `speed` (microsteps per second).

Faults (URL `fault=` or the saved state's "faults", set with `benchctl sim fault <name> ...`):
  no_reply        the controller is deaf: nothing is executed or answered
  garbled         replies arrive with every byte corrupted; line endings intact
  slow            replies come SLOW_REPLY_DELAY_S late
  stall           every move stops half-way with the stall warning FS (a jammed carriage)
  drop_after=N    the line back to the host is cut after N commands: the stage still obeys, replies are lost
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

from benchctl.devices.sim import laser_emulators
from benchctl.devices.sim.focus_mechanics import Mechanism
from benchctl.devices.sim.state import load_state, save_state
from benchctl.profiles import SimFocusConfig

FAULTS = ("no_reply", "garbled", "slow", "stall", "drop_after=N")
SLOW_REPLY_DELAY_S = 2.0
DEFAULT_SPEED = 200000.0  # microsteps per second
SERIAL = "4242"
VERSION = "7.38"
_OPTIONS = ("fault", "reply_delay_s", "speed")


def parse_faults(items: list[str]) -> tuple[frozenset[str], int | None]:
    """The stage's fault names as a set, plus N of drop_after=N; ValueError names a bad one."""
    return laser_emulators.parse_faults(items, FAULTS)


def _number(text: str, name: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"option {name}={text!r} is not a number") from None


class ZaberStage:
    """One controller with one axis (device 1, axis 1) on a simulated line; see the module docstring."""

    def __init__(self, name: str, params: Mapping[str, str], config: SimFocusConfig | None = None) -> None:
        unknown = sorted(set(params) - set(_OPTIONS))
        if unknown:
            raise ValueError(f"unknown option {unknown[0]!r} (known: dialect, {', '.join(_OPTIONS)})")
        self.name = name
        saved = load_state(name)
        self.faults, self.drop_after = parse_faults(params.get("fault", "").split(",") + list(saved.get("faults", [])))
        delay = params.get("reply_delay_s")
        self.reply_delay_s = _number(delay, "reply_delay_s") if delay else (
            SLOW_REPLY_DELAY_S if "slow" in self.faults else 0.0)
        self.speed = _number(params.get("speed", str(DEFAULT_SPEED)), "speed")
        if self.speed <= 0:
            raise ValueError(f"option speed={self.speed:g} must be > 0")
        self.mechanism = Mechanism(config)
        self.state: dict[str, Any] = {"kind": "focus", "dialect": "zaber", "faults": list(saved.get("faults", [])),
                                      "position": int(saved.get("position", 0)), "homed": bool(saved.get("homed"))}
        self.busy_until = 0.0
        self.warning = "--" if self.state["homed"] else "WR"
        self.commands = 0
        self._inbox = bytearray()

    @property
    def limit_max(self) -> int:
        return self.mechanism.config.range_steps

    # -- bytes in, bytes out -----------------------------------------------------------------------------------

    def receive(self, data: bytes) -> bytes:
        """Take bytes from the host; return the reply lines to every complete command."""
        self._inbox += data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
        out = bytearray()
        while (end := self._inbox.find(b"\n")) >= 0:
            raw = bytes(self._inbox[:end])
            del self._inbox[:end + 1]
            out += self._respond(raw.decode("ascii", "replace"))
        return bytes(out)

    def _respond(self, line: str) -> bytes:
        self.commands += 1
        if "no_reply" in self.faults:
            return b""
        reply = self.handle(line)
        if reply is None or (self.drop_after is not None and self.commands > self.drop_after):
            return b""
        encoded = reply.encode("ascii")
        if "garbled" in self.faults:
            encoded = bytes(b | 0x80 for b in encoded)
        return encoded + b"\r\n"

    def handle(self, line: str) -> str | None:
        """The reply line to one command (None: not for this device, so no reply)."""
        if not line.startswith("/"):
            return None
        words = line[1:].split()
        device = int(words.pop(0)) if words and words[0].isdigit() else 0
        axis = int(words.pop(0)) if words and words[0].isdigit() else 0
        if device not in (0, 1):
            return None
        command = " ".join(words)
        busy = time.monotonic() < self.busy_until
        flag, data = "OK", "0"
        if command == "":
            pass
        elif command == "home":
            self._move_to(0, homing=True)
        elif command in ("stop", "warnings clear"):
            if command == "warnings clear":
                data = f"{0 if self.warning == '--' else 1:02d}" + ("" if self.warning == "--" else f" {self.warning}")
                self.warning = "--" if self.state["homed"] else "WR"
            else:
                self.busy_until = 0.0
        elif command == "warnings":
            data = "00" if self.warning == "--" else f"01 {self.warning}"
        elif command.startswith("move abs ") or command.startswith("move rel "):
            try:
                value = int(command.split()[2])
            except (IndexError, ValueError):
                return self._reply(axis, "RJ", busy, "BADDATA")
            target = value if command.startswith("move abs") else self.state["position"] + value
            if not 0 <= target <= self.limit_max:
                return self._reply(axis, "RJ", busy, "BADDATA")
            self._move_to(target)
        elif command == "get pos":
            data = str(self.state["position"])
        elif command == "get limit.min":
            data = "0"
        elif command == "get limit.max":
            data = str(self.limit_max)
        elif command == "get system.serial":
            data = SERIAL
        elif command == "get version":
            data = VERSION
        else:
            return self._reply(axis, "RJ", busy, "BADCOMMAND")
        return self._reply(axis, flag, time.monotonic() < self.busy_until, data)

    def _reply(self, axis: int, flag: str, busy: bool, data: str) -> str:
        return f"@01 {axis} {flag} {'BUSY' if busy else 'IDLE'} {self.warning} {data}"

    def _move_to(self, target: int, homing: bool = False) -> None:
        """Start a move: the counter goes to `target` (half-way with the stall fault), the carriage follows with the
        mechanism's backlash; homing drives to the home sensor at the end stop and clears WR."""
        start = self.state["position"]
        if "stall" in self.faults:
            target = start + (target - start) // 2
            self.warning = "FS"
        steps = target - start
        if homing:
            self.mechanism.drive(-(self.mechanism.true_steps + self.mechanism.config.backlash_steps + 1))
            self.mechanism.drive(1)  # off the sensor's edge: the home position is approached from above, then left
            self.mechanism.drive(-1)
            self.state["homed"] = True
            if self.warning == "WR":
                self.warning = "--"
            steps = start
            target = 0
        else:
            self.mechanism.drive(steps)
        self.state["position"] = target
        self.busy_until = time.monotonic() + abs(steps) / self.speed
        save_state(self.name, {**load_state(self.name), **self.state})
