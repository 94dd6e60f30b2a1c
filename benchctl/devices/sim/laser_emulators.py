"""Byte-level emulators of the laser units benchctl drives, so drivers are tested against the real wire protocols.

Each emulator is the firmware of one unit: bytes in, bytes out, commands framed by the exact line ending, the
dialect's OK lines and error replies. One shared model holds what a unit remembers (setpoints, emission,
autostart), persisted with state.save_state after every change and loaded when the port opens, so a setting
made by one benchctl process is seen by the next, as with hardware.

Dialects (sim:// `dialect=`): `template` (the default: the command set of hardware_profiles/simulated.toml,
three channels), `cobolt`, `sapphire` and `deepstar` (one head per port) and `obis` (one head per port;
`channels=N` makes a multi-head box addressed as `SOURce2:...`).

Faults, from the URL (`fault=a,b`) and from the saved state's "faults" list (so the CLI can set them):
  no_reply        the unit is deaf: commands are neither executed nor answered
  garbled         replies arrive with every byte corrupted (as with a wrong baud rate); line endings intact
  echo            the unit echoes each command line before its reply
  slow            replies come after reply_delay_s (default SLOW_REPLY_DELAY_S); reply_delay_s alone also delays
  interlock_open  the interlock is open: emission is refused the way the real unit refuses it
  device_fault    a fault is active (temperature): reported by the status query, emission refused
  clamp           setpoints are silently clamped to half the unit's max power
  drop_after=N    the line back to the host is cut after N commands: the unit still obeys, replies are lost
                  (so tests can see that a driver still sends emission-off on its way out)
"""

from __future__ import annotations

import math
import re
import zlib
from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Any, ClassVar

from benchctl.devices.sim.state import load_state, save_state

FAULTS = ("no_reply", "garbled", "echo", "slow", "interlock_open", "device_fault", "clamp", "drop_after=N")
SLOW_REPLY_DELAY_S = 2.0
DEFAULT_MAX_MW = 40.0
_OPTIONS = ("fault", "reply_delay_s", "max_mw", "channels")


def parse_faults(items: list[str], known: tuple[str, ...] = FAULTS) -> tuple[frozenset[str], int | None]:
    """Fault names (see the module docstring; `known`: another simulator's) as a set, plus N of drop_after=N;
    ValueError names a bad one."""
    names: set[str] = set()
    drop_after = None
    for item in (raw.strip() for raw in items):
        if not item:
            continue
        if item.startswith("drop_after="):
            try:
                drop_after = int(item.split("=", 1)[1])
            except ValueError:
                raise ValueError(f"fault {item!r}: N in drop_after=N must be an integer") from None
        elif item in known:
            names.add(item)
        else:
            raise ValueError(f"unknown fault {item!r} (known: {', '.join(known)})")
    return frozenset(names), drop_after


class LaserEmulator(ABC):
    """One simulated laser unit: line framing, faults and the persisted model; dialects implement `handle`."""

    dialect: ClassVar[str]
    default_channels: ClassVar[int] = 1
    terminator: ClassVar[bytes] = b"\r\n"
    settings: ClassVar[dict[str, Any]] = {}  # what else the unit remembers (name: factory default)

    def __init__(self, name: str, params: Mapping[str, str]) -> None:
        unknown = sorted(set(params) - set(_OPTIONS))
        if unknown:
            raise ValueError(f"unknown option {unknown[0]!r} (known: dialect, {', '.join(_OPTIONS)})")
        self.name = name
        saved = load_state(name)
        fault_items = params.get("fault", "").split(",") + list(saved.get("faults", []))
        self.faults, self.drop_after = parse_faults(fault_items)
        delay = params.get("reply_delay_s")
        self.reply_delay_s = _number(delay, "reply_delay_s") if delay else (
            SLOW_REPLY_DELAY_S if "slow" in self.faults else 0.0)
        self.max_w = _number(params.get("max_mw", str(DEFAULT_MAX_MW)), "max_mw") * 1e-3
        saved_channels: dict[str, Any] = saved.get("channels", {})
        count = int(_number(params.get("channels", "0"), "channels")) or len(saved_channels) or self.default_channels
        self.state: dict[str, Any] = {
            "kind": "laser",
            "dialect": self.dialect,
            "autostart": saved.get("autostart", True),  # factory default, which is why drivers turn it off
            "faults": list(saved.get("faults", [])),
            **{key: saved.get(key, default) for key, default in self.settings.items()},
            "channels": {
                str(i): {"setpoint_w": 0.0, "emission": False, **saved_channels.get(str(i), {})}
                for i in range(1, count + 1)
            },
        }
        self.commands = 0
        self._inbox = bytearray()

    # -- bytes in, bytes out -----------------------------------------------------------------------------------

    def receive(self, data: bytes) -> bytes:
        """Take bytes from the host; return the bytes the unit sends back (replies to every complete line)."""
        self._inbox += data
        out = bytearray()
        while (end := self._inbox.find(self.terminator)) >= 0:
            raw = bytes(self._inbox[:end])
            del self._inbox[: end + len(self.terminator)]
            out += self._respond(raw)
        return bytes(out)

    def _respond(self, raw: bytes) -> bytes:
        self.commands += 1
        if "no_reply" in self.faults:
            return b""
        line = raw.decode("ascii", "replace")
        lines = ([line] if "echo" in self.faults else []) + self.handle(line)
        if self.drop_after is not None and self.commands > self.drop_after:
            return b""
        reply = b"".join(text.encode("ascii", "replace") + self.terminator for text in lines) + self.trailer()
        if "garbled" in self.faults:
            reply = bytes(b | 0x80 if b not in self.terminator else b for b in reply)
        return reply

    def trailer(self) -> bytes:
        """What the unit sends after each reply's lines (a prompt, with no line ending). Default: nothing."""
        return b""

    @abstractmethod
    def handle(self, line: str) -> list[str]:
        """The reply lines to one command line (without terminators)."""

    # -- the model every dialect shares ------------------------------------------------------------------------

    @property
    def channel_count(self) -> int:
        return len(self.state["channels"])

    def channel(self, index: int) -> dict[str, Any] | None:
        """The saved state of channel `index` (from 1), or None if the unit has no such channel."""
        return self.state["channels"].get(str(index))

    @property
    def interlock_open(self) -> bool:
        return "interlock_open" in self.faults

    @property
    def fault_active(self) -> bool:
        return "device_fault" in self.faults

    @property
    def serial_number(self) -> str:
        """A stable serial number derived from the device name."""
        return str(10000 + zlib.crc32(self.name.encode()) % 90000)

    def set_setpoint(self, index: int, watts: float) -> bool:
        """Store a setpoint (clamped to half the max under the `clamp` fault); False if out of range."""
        if not (0.0 <= watts <= self.max_w * (1 + 1e-9)):
            return False
        if "clamp" in self.faults:
            watts = min(watts, self.max_w / 2)
        self._change(index, setpoint_w=watts)
        return True

    def set_emission(self, index: int, on: bool) -> str | None:
        """Switch emission; refused (returns "interlock" or "fault", emission stays off) as the real unit would."""
        if on and self.interlock_open:
            return "interlock"
        if on and self.fault_active:
            return "fault"
        self._change(index, emission=on)
        return None

    def set_autostart(self, on: bool) -> None:
        self.state["autostart"] = on
        self.save()

    def measured_w(self, index: int) -> float:
        """The setpoint while emitting (with a small deterministic ripple), else 0."""
        channel = self.channel(index)
        if channel is None or not channel["emission"]:
            return 0.0
        return channel["setpoint_w"] * (1 + 1e-3 * math.sin(self.commands))

    def _change(self, index: int, **values: Any) -> None:
        self.state["channels"][str(index)].update(values)
        self.save()

    def save(self) -> None:
        save_state(self.name, self.state)


def _number(text: str, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{what} must be a number, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{what} must be a finite number >= 0, got {text!r}")
    return value


def _float_or_none(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


class TemplateEmulator(LaserEmulator):
    """The simulated RGB unit: `CH{n}:POW {mw}`, `CH{n}:POW?`, `CH{n}:MEAS?`, `CH{n}:EMIT 1|0`, `CH{n}:EMIT?`,
    `CH{n}:STAT?`, `*IDN?`; non-queries answer `OK`, errors `ERR <code> <text>`; powers in mW."""

    dialect = "template"
    default_channels = 3
    _COMMAND = re.compile(r"CH(?P<index>\d+):(?P<key>POW|MEAS|EMIT|STAT)(?P<rest>\?| .*)")
    _REFUSED: ClassVar[dict[str, str]] = {"interlock": "ERR 3 INTERLOCK", "fault": "ERR 4 FAULT ACTIVE"}

    def handle(self, line: str) -> list[str]:
        if line == "*IDN?":
            return [f"benchctl,simulated RGB laser,{self.serial_number},{self.channel_count} channels"]
        match = self._COMMAND.fullmatch(line)
        if match is None:
            return ["ERR 1 UNKNOWN COMMAND"]
        index, key, rest = int(match["index"]), match["key"], match["rest"]
        channel = self.channel(index)
        if channel is None:
            return ["ERR 5 NO SUCH CHANNEL"]
        if rest == "?":
            if key == "POW":
                return [f"{channel['setpoint_w'] * 1e3:.3f}"]
            if key == "MEAS":
                return [f"{self.measured_w(index) * 1e3:.3f}"]
            if key == "EMIT":
                return ["1" if channel["emission"] else "0"]
            return ["INTERLOCK OPEN" if self.interlock_open else "FAULT 1 TEMPERATURE" if self.fault_active else "OK"]
        arg = rest[1:]
        if key == "POW":
            mw = _float_or_none(arg)
            return ["OK" if mw is not None and self.set_setpoint(index, mw * 1e-3) else "ERR 2 OUT OF RANGE"]
        if key == "EMIT" and arg in ("0", "1"):
            refused = self.set_emission(index, arg == "1")
            return [self._REFUSED[refused] if refused else "OK"]
        return ["ERR 1 UNKNOWN COMMAND"]


class CoboltEmulator(LaserEmulator):
    """A Cobolt head: `p <W>` / `@cobasp <W>`, `p?`, `pa?`, `l1` / `l0`, `l?`, `f?`, `ilk?`, `cf`, `@cobas 0|1`,
    `gsn?`, `gmlp?` (mW); non-queries answer `OK`, bad commands `Syntax error: ...`. With the interlock open or a
    fault active, `l1` answers OK and emission stays off (f? tells why: 3 interlock, 1 temperature)."""

    dialect = "cobolt"

    def handle(self, line: str) -> list[str]:
        channel = self.channel(1)
        assert channel is not None
        queries = {
            "p?": lambda: f"{channel['setpoint_w']:.6f}",
            "pa?": lambda: f"{self.measured_w(1):.6f}",
            "l?": lambda: "1" if channel["emission"] else "0",
            "f?": lambda: "3" if self.interlock_open else "1" if self.fault_active else "0",
            "ilk?": lambda: "1" if self.interlock_open else "0",
            "@cobas?": lambda: "1" if self.state["autostart"] else "0",
            "gsn?": lambda: self.serial_number,
            "gmlp?": lambda: f"{self.max_w * 1e3:.6f}",
        }
        if line in queries:
            return [queries[line]()]
        if line in ("l1", "l0"):
            self.set_emission(1, line == "l1")  # a refused l1 still answers OK: only l? and f? show it
            return ["OK"]
        if line in ("@cobas 0", "@cobas 1"):
            self.set_autostart(line.endswith("1"))
            return ["OK"]
        if line == "cf":
            return ["OK"]  # injected faults persist: clearing cannot fix them
        command, _, arg = line.partition(" ")
        if command in ("p", "@cobasp") and arg:
            watts = _float_or_none(arg)
            if watts is None:
                return ["Syntax error: illegal command"]
            return ["OK" if self.set_setpoint(1, watts) else "Syntax error: value out of range"]
        return ["Syntax error: illegal command"]


class SapphireEmulator(LaserEmulator):
    """A Coherent Sapphire head, powers in mW: `P=<mW>`, `?SP`, `?P`, `?MAXLP`, `?MINLP` (0 here), `L=1` / `L=0`, `?L`,
    `?K` (key on: 1), `?FF` (bit 0 interlock, bit 1 diode temperature, bit 13 laser ready), `?HID`, `?STA`. Out of the
    box it echoes each command and prompts with `Sapphire:0-> `; `E=0` / `E=1` and `>=0` / `>=1` switch them (kept,
    like the other settings). With echo off it still returns each command's line ending (an empty line). A setting
    made with the light off answers a note; `L=1` with the interlock open or a fault leaves the light off."""

    dialect = "sapphire"
    settings: ClassVar[dict[str, Any]] = {"echo": True, "prompt": True}
    PROMPT = b"Sapphire:0-> "

    def handle(self, line: str) -> list[str]:
        echoed = line if self.state["echo"] else ""  # the head echoes as it receives, before it obeys
        return [echoed, *self._answer(line.strip().upper())]

    def trailer(self) -> bytes:
        return self.PROMPT if self.state["prompt"] else b""

    def _answer(self, command: str) -> list[str]:
        channel = self.channel(1)
        assert channel is not None
        queries = {
            "?HID": lambda: self.serial_number,
            "?K": lambda: "1",
            "?L": lambda: "1" if channel["emission"] else "0",
            "?SP": lambda: f"{channel['setpoint_w'] * 1e3:.3f}",
            "?P": lambda: f"{self.measured_w(1) * 1e3:.3f}",
            "?MAXLP": lambda: f"{self.max_w * 1e3:.3f}",
            "?MINLP": lambda: "0.000",
            "?FF": lambda: str(self.interlock_open * 1 + self.fault_active * 2 + channel["emission"] * 8192),
            "?STA": lambda: "5",
        }
        if command in queries:
            return [queries[command]()]
        switches = {"E=": "echo", ">=": "prompt", "L=": "light"}
        if command[:2] in switches and command[2:] in ("0", "1"):
            if switches[command[:2]] == "light":
                self.set_emission(1, command[2:] == "1")  # refused: the light stays off, ?L and ?FF tell why
            else:
                self.state[switches[command[:2]]] = command[2:] == "1"
                self.save()
            return []
        if command.startswith("P="):
            milliwatts = _float_or_none(command[2:])
            if milliwatts is None or not self.set_setpoint(1, milliwatts * 1e-3):
                return [f"value must be between 0.000 and {self.max_w * 1e3:.3f}"]
            return [] if channel["emission"] else ["Note: Laser_Output is OFF (L=0)"]
        return ["Invalid command"]


class DeepstarEmulator(LaserEmulator):
    """An Omicron Deepstar head: fixed-length commands (14 characters, space padded, then CR LF; any other length is
    refused with `UK`), states S0 (interlock open or a fault), S1 (standby), S2 (laser on: emission). `S?`, `LON`
    (`LONOK`, `INT` in S0, `UK` in S2), `LF` (`LOFFOK`, `UK` unless in S2), modes `L0` / `BLK` / `LB` / `L1` / `L2`
    (`>` in S2, else `UK`), `IPO` / `IPF`, `PP<3 hex>` (echoed) / `PP?` (0xFFF: the maximum), `P?` (0xCCC: the
    maximum), `STAT0` (model code: 488 nm, the maximum in mW), `STAT2` (serial numbers)."""

    dialect = "deepstar"
    settings: ClassVar[dict[str, Any]] = {"mode": "L0", "internal_peak_power": False}
    WIDTH = 14

    def handle(self, line: str) -> list[str]:
        if len(line) != self.WIDTH:
            return ["UK"]
        command = line.rstrip(" ")
        channel = self.channel(1)
        assert channel is not None
        state = "S0" if self.interlock_open or self.fault_active else "S2" if channel["emission"] else "S1"
        max_mw = self.max_w * 1e3
        if command == "S?":
            return [state]
        if command == "STAT0":
            return [f"MC 488  {max_mw:3.0f} TA   "]
        if command == "STAT2":
            return [f"R111 N02 SNP{self.serial_number} SNC{self.serial_number} WH 00000"]
        if command == "LON":
            if state == "S1":
                self.set_emission(1, True)
            return [{"S0": "INT", "S1": "LONOK", "S2": "UK"}[state]]
        if command == "LF":
            if state != "S2":
                return ["UK"]
            self.set_emission(1, False)
            return ["LOFFOK"]
        if command in ("L0", "BLK", "LB", "L1", "L2"):
            if state != "S2":
                return ["UK"]
            self.state["mode"] = "L0" if command == "BLK" else command
            self.save()
            return [">"]
        if command in ("IPO", "IPF"):
            self.state["internal_peak_power"] = command == "IPO"
            self.save()
            return [command]
        if command == "PP?":
            return [f"PP{round(channel['setpoint_w'] / self.max_w * 0xFFF):03X}"]
        if command == "P?":
            return [f"P{round(self.measured_w(1) / self.max_w * 0xCCC):04X}"]
        if re.fullmatch(r"PP[0-9A-F]{3}", command):
            self.set_setpoint(1, int(command[2:], 16) / 0xFFF * self.max_w)
            return [command]
        return ["UK"]


class _ParameterError(Exception):
    """An OBIS command with a parameter the head does not accept (answered ERR-220)."""


class ObisEmulator(LaserEmulator):
    """A Coherent OBIS head (or a box of heads, `SOURce{n}:...`), handshaking on: each reply is followed by `OK`,
    errors are `ERR-<code>` (100 unrecognised command, 220 invalid parameter). SCPI keywords match in short or
    long form, any case. Emission refused with the interlock open or a fault active: stays off, answers OK."""

    dialect = "obis"
    _FAULT_BASE_PLATE_TEMPERATURE = 0x1

    def __init__(self, name: str, params: Mapping[str, str]) -> None:
        super().__init__(name, params)
        # (header spec, action(head index, argument) -> the reply value, or None for a setting)
        self._commands = [(_scpi(spec), action) for spec, action in (
            ("*IDN?", lambda i, arg: f"Coherent, Inc - OBIS (simulated) - {self.serial_number}"),
            ("SYSTem:AUTostart", lambda i, arg: self.set_autostart(_on_off(arg))),
            ("SYSTem:AUTostart?", lambda i, arg: "ON" if self.state["autostart"] else "OFF"),
            ("SYSTem:CDRH", lambda i, arg: self._accept(_on_off(arg))),
            ("SYSTem:FAULt?", lambda i, arg: f"0x{self._fault_code():08X}"),
            ("SYSTem:LOCK?", lambda i, arg: "OFF" if self.interlock_open else "ON"),
            ("SOURce:POWer:LEVel[:IMMediate]:AMPLitude", self._set_power),
            ("SOURce:POWer:LEVel[:IMMediate]:AMPLitude?", lambda i, arg: f"{self._head(i)['setpoint_w']:.6f}"),
            ("SOURce:POWer:LEVel?", lambda i, arg: f"{self.measured_w(i):.6f}"),
            ("SOURce:POWer:LIMit:HIGH?", lambda i, arg: f"{self.max_w:.6f}"),
            ("SOURce:POWer:LIMit:LOW?", lambda i, arg: "0.000000"),
            ("SOURce:AM:STATe", self._set_emission),
            ("SOURce:AM:STATe?", lambda i, arg: "ON" if self._head(i)["emission"] else "OFF"),
        )]

    def handle(self, line: str) -> list[str]:
        header, _, arg = line.strip().partition(" ")
        arg = arg.strip()
        for pattern, action in self._commands:
            match = pattern.fullmatch(header)
            if match is None:
                continue
            index = int(match.groupdict().get("index") or 1)
            if self.channel(index) is None or header.endswith("?") == bool(arg):
                return ["ERR-220"]  # no such head, a query with an argument or a setting without one
            try:
                reply = action(index, arg)
            except _ParameterError:
                return ["ERR-220"]
            return ["OK"] if reply is None else [reply, "OK"]
        return ["ERR-100"]

    def _head(self, index: int) -> dict[str, Any]:
        channel = self.channel(index)
        assert channel is not None  # checked by handle
        return channel

    def _fault_code(self) -> int:
        return self._FAULT_BASE_PLATE_TEMPERATURE if self.fault_active else 0

    def _accept(self, setting: bool) -> None:
        """A setting the simulation has no use for (CDRH delay): checked, then ignored."""

    def _set_emission(self, index: int, arg: str) -> None:
        self.set_emission(index, _on_off(arg))  # a refused ON still answers OK: emission stays off

    def _set_power(self, index: int, arg: str) -> None:
        watts = _float_or_none(arg)
        if watts is None or not self.set_setpoint(index, watts):
            raise _ParameterError(arg)


def _on_off(arg: str) -> bool:
    try:
        return {"ON": True, "OFF": False}[arg.upper()]
    except KeyError:
        raise _ParameterError(arg) from None


def _scpi(spec: str) -> re.Pattern[str]:
    """A regex for a SCPI header spec: each keyword in short (capitals) or long form, any case; `[:KEY]` optional;
    the first keyword may carry a head number (`SOURce2`), captured as `index`."""
    if spec.startswith("*"):
        return re.compile(re.escape(spec), re.IGNORECASE)
    query = spec.endswith("?")
    parts = []
    for i, token in enumerate(re.findall(r"\[?:?\w+\]?", spec.rstrip("?"))):
        optional = token.startswith("[")
        word = token.strip("[]:")
        short = "".join(c for c in word if c.isupper())
        alternatives = f"(?:{short}|{word.upper()})" if short != word.upper() else word.upper()
        piece = alternatives + ("(?P<index>\\d*)" if i == 0 else "")
        piece = piece if i == 0 else f":{piece}"
        parts.append(f"(?:{piece})?" if optional else piece)
    return re.compile("".join(parts) + ("\\?" if query else ""), re.IGNORECASE)


DIALECTS: dict[str, type[LaserEmulator]] = {
    cls.dialect: cls for cls in (TemplateEmulator, CoboltEmulator, ObisEmulator, SapphireEmulator, DeepstarEmulator)
}


def make_emulator(name: str, params: Mapping[str, str]) -> LaserEmulator:
    """The emulator for simulated device `name` from its sim:// URL parameters; ValueError names a bad one."""
    dialect = params.get("dialect", "template")
    if dialect not in DIALECTS:
        raise ValueError(f"unknown dialect {dialect!r} (known: {', '.join(DIALECTS)})")
    return DIALECTS[dialect](name, {k: v for k, v in params.items() if k != "dialect"})
