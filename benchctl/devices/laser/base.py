"""The Laser device: a multi-wavelength source with named channels, and the safety rules every driver obeys.

The public methods are fixed here and drivers implement small hooks (one command each, mostly), so the safety
rules live in one place and cannot be skipped by a dialect:
- connecting turns autostart off (where the dialect has it) and emission off on every channel, read back, and
  reports each channel it found emitting (`connect_report`);
- a power above the channel's max_power_mw (or the head's own limit) is refused before anything is sent;
- every setting is read back; a device that silently clamps or ignores a setting is an error;
- emission is enabled only after the interlock and fault status were checked;
- leaving a `with` block, normally or by any exception (KeyboardInterrupt and lost replies included), turns
  emission off on every channel, trying each one even when an earlier one fails;
- before emission first goes on, a watchdog process is started that switches it off through the same driver if
  this process dies without closing the laser (SIGKILL, a native crash: benchctl.devices.watchdog).
"""

from __future__ import annotations

import contextlib
import math

import msgspec
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from types import TracebackType
from typing import TypeVar

from benchctl.devices.errors import DeviceError, EmissionNotOff, SafetyError
from benchctl.devices.lock import DeviceLock
from benchctl.devices.power import format_power, parse_power
from benchctl.devices.serial_link import SerialLink, SerialPort
from benchctl.devices.watchdog import Watchdog
from benchctl.errors import BadValueError, BenchctlError
from benchctl.profiles import LaserChannel, LaserConfig

# A setpoint read back within this of the request is the request (devices round to their resolution):
# the larger of a relative share of the request and a share of the channel's full scale.
SETPOINT_RELATIVE_TOLERANCE = 0.01
SETPOINT_FULL_SCALE_TOLERANCE = 0.001

UNKNOWN_EMISSION = "emission state UNKNOWN, possibly ON: use the key switch / interlock"

PortFactory = Callable[[str], SerialPort]
T = TypeVar("T")


@dataclass(frozen=True)
class ChannelStatus:
    """One channel as the device reports it. interlock_ok is None where the dialect cannot tell."""

    name: str
    wavelength_nm: float
    setpoint_w: float
    measured_w: float | None
    emission: bool
    interlock_ok: bool | None
    faults: tuple[str, ...]


class Laser(ABC):
    """A laser unit built from a profile's LaserConfig; use it as a context manager (see the module docstring).

    Drivers set the class attributes of their line protocol and implement the hooks (methods starting with `_`
    and marked abstract); channels on one port share one SerialLink.
    """

    # The line protocol (class defaults; the template driver takes them from the profile per instance).
    line_ending: str = "\r\n"
    ok_reply: str = "OK"
    error_prefix: str | None = None
    echo: bool = False
    one_head_per_port: bool = False  # single-wavelength heads: every channel needs a port of its own

    def __init__(self, config: LaserConfig, *, leave_on: bool = False, observe: bool = False,
                 port_factory: PortFactory | None = None) -> None:
        """`leave_on`: a plain close() leaves emission as it is (an exception inside `with` still turns it off).
        `observe`: connect to read only (status, identity): nothing is changed at connect or on a plain close,
        and setting power or enabling emission is refused; switching emission off is always allowed.
        `port_factory`: url -> an open port, instead of opening real ones (tests use an expected-protocol port)."""
        self.config = config
        self.leave_on = leave_on
        self.observe = observe
        self._port_factory = port_factory
        self._channels = {channel.name: channel for channel in config.channels}
        self._ports: dict[str, list[LaserChannel]] = {}
        for channel in config.channels:
            self._ports.setdefault(config.port_of(channel), []).append(channel)
        for port, sharing in self._ports.items():
            if self.one_head_per_port and len(sharing) > 1:
                raise BenchctlError(f"{config.driver} laser: channels {', '.join(ch.name for ch in sharing)} share "
                                    f"port {port}, but a {config.driver} head has one wavelength: give each channel "
                                    "its own port")
        self._links: dict[str, SerialLink] = {}
        self._holds: dict[str, DeviceLock] = {}
        self._limits_w: dict[str, float] = {}
        self._emission_commanded: dict[str, bool] = {}
        self.found_emitting: dict[str, float] = {}  # channel -> setpoint (W) of channels emitting at connect
        self._watchdog: Watchdog | None = None  # started before emission first goes on (real ports only)

    # -- connection ------------------------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        return bool(self._links)

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(self._channels)

    def open(self) -> Laser:
        """Connect, then make safe: autostart off, emission off on every channel (read back); learn head limits.
        In observe mode: connect only."""
        if self.is_open:
            return self
        failure: BaseException | None = None
        for url, channels in self._ports.items():
            try:
                self._holds[url] = port_lock(url).acquire()
                port = self._port_factory(url) if self._port_factory else None
                self._links[url] = SerialLink(
                    url, baudrate=self.config.baudrate, timeout_s=self.config.timeout_s, line_ending=self.line_ending,
                    write_delay_s=self.config.write_delay_s, echo=self.echo, error_prefix=self.error_prefix,
                    name=f"{self.config.driver} laser {'/'.join(ch.name for ch in channels)}", port=port,
                )
            except BaseException as exc:  # still make the reachable heads safe before reporting it
                failure = failure or exc
        reachable = [ch for ch in self.config.channels if self.config.port_of(ch) in self._links]
        if not self.observe:
            try:
                try_each(self._make_safe, reachable)
            except BaseException as exc:
                failure = failure or exc
        if failure is not None:
            self._close_links()
            raise failure
        return self

    def close(self) -> None:
        """Emission off on every channel (unless leave_on or observe), then close the ports; every channel is
        tried before the first error is raised."""
        self._shutdown(emission_off=not (self.leave_on or self.observe))

    def __enter__(self) -> Laser:
        return self.open()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._shutdown(emission_off=exc_type is not None or not (self.leave_on or self.observe))

    def _shutdown(self, *, emission_off: bool) -> None:
        if not self.is_open:
            return
        try:
            if emission_off:
                self.all_off()
        finally:
            self._close_links()

    def _close_links(self) -> None:
        links, self._links = self._links, {}
        holds, self._holds = self._holds, {}
        watchdog, self._watchdog = self._watchdog, None
        try:
            try_each(SerialLink.close, links.values())
        finally:
            try:
                try_each(DeviceLock.release, holds.values())
            finally:
                if watchdog is not None:  # an orderly close, which said what it knows of emission
                    watchdog.disarm()

    def _arm_watchdog(self) -> None:
        """Start the watchdog unless one runs; ports made by a port_factory (tests' scripted ports) are not reachable
        from another process, so they have none. DeviceError when it cannot start (emission then stays off)."""
        if self._watchdog is not None or self._port_factory is not None:
            return
        try:
            self._watchdog = Watchdog(msgspec.json.encode(self.config))
        except OSError as exc:
            raise DeviceError(f"{self.config.driver} laser: cannot start the watchdog that switches emission off if "
                              f"this process dies ({exc}): emission not enabled") from None

    def _make_safe(self, channel: LaserChannel) -> None:
        try:
            self._prepare(channel)
            was_on = self._read_emission(channel)
        finally:
            self._switch_off(channel)
        if was_on:
            self.found_emitting[channel.name] = self._read_setpoint(channel)
        limit = self._read_limit_w(channel)
        if limit is not None:
            self._limits_w[channel.name] = limit

    # -- public API --------------------------------------------------------------------------------------------

    def connect_report(self) -> list[str]:
        """One line per channel that was emitting when this connection switched it off (every command says it:
        something left the light on)."""
        return [f"{name} was emitting at {format_power(watts)}; switched off"
                for name, watts in self.found_emitting.items()]

    def identity(self) -> str:
        """What the unit says it is (model, serial number), one entry per port for multi-port setups."""
        self._require_open()
        parts = [(channels, self._identify(channels[0])) for channels in self._ports.values()]
        if len(parts) == 1:
            return parts[0][1]
        return "; ".join(f"{'/'.join(ch.name for ch in channels)}: {text}" for channels, text in parts)

    def set_power(self, channel: str, power: str | float) -> float:
        """Set a channel's setpoint and return it as read back (W). `power` is a string with a unit ("20mW",
        "5%"; see parse_power) or a number of watts. Above the channel's limit: SafetyError, nothing sent."""
        ch = self._channel(channel)
        watts = parse_power(power, ch.max_power_mw) if isinstance(power, str) else float(power)
        if not (math.isfinite(watts) and watts >= 0):
            raise BadValueError(
                f"laser channel {ch.name!r}: power must be a finite number of watts >= 0, got {power!r}"
            )
        limit_w = ch.max_power_mw * 1e-3
        if watts > limit_w * (1 + 1e-9):
            raise SafetyError(
                f"laser channel {ch.name!r}: {format_power(watts)} is above the profile's limit "
                f"{format_power(limit_w)} (max_power_mw); nothing was sent"
            )
        self._require_writable()
        head_limit_w = self._limits_w.get(ch.name)
        if head_limit_w is not None and watts > head_limit_w * (1 + 1e-9):
            raise DeviceError(
                f"{self._where(ch)}: {format_power(watts)} is above the head's own limit {format_power(head_limit_w)}; "
                "nothing was sent"
            )
        self._write_power(ch, watts)
        held = self._read_setpoint(ch)
        tolerance = max(SETPOINT_RELATIVE_TOLERANCE * watts, SETPOINT_FULL_SCALE_TOLERANCE * limit_w,
                        self._setpoint_step_w(ch) / 2 * (1 + 1e-9))
        if abs(held - watts) > tolerance:
            raise DeviceError(
                f"{self._where(ch)}: asked for {format_power(watts)}, the device holds {format_power(held)} "
                "(it clamped or ignored the setting)"
            )
        return held

    def setpoint_w(self, channel: str) -> float:
        """The setpoint the device holds (W)."""
        ch = self._channel(channel)
        self._require_open()
        return self._read_setpoint(ch)

    def measured_w(self, channel: str) -> float | None:
        """The output power the device measures (W), or None where the dialect cannot report it."""
        ch = self._channel(channel)
        self._require_open()
        return self._read_measured(ch)

    def set_emission(self, channel: str, on: bool) -> None:
        """Switch a channel's emission and read it back. On: the interlock and faults are checked first (open
        interlock or active fault: SafetyError, nothing enabled); if anything fails after enabling, it is
        switched off again before the error is raised."""
        ch = self._channel(channel)
        self._require_open()
        if not on:
            self._switch_off(ch)
            return
        self._require_writable()
        interlock_ok, faults = self._read_health(ch)
        if interlock_ok is False:
            raise SafetyError(f"{self._where(ch)}: interlock open: emission not enabled")
        if faults:
            raise SafetyError(f"{self._where(ch)}: fault active ({'; '.join(faults)}): emission not enabled")
        self._arm_watchdog()
        try:
            self._write_emission(ch, True)
            self._emission_commanded[ch.name] = True
            if self._read_emission(ch) is False:
                raise DeviceError(f"{self._where(ch)}: emission did not turn on (the device reports it off)")
        except BaseException:
            with contextlib.suppress(Exception):  # the first error says more; close() tries again
                self._switch_off(ch)
            raise

    def emission(self, channel: str) -> bool:
        """Whether the channel emits, as the device reports (the last command where the dialect cannot tell)."""
        ch = self._channel(channel)
        self._require_open()
        state = self._read_emission(ch)
        return self._emission_commanded.get(ch.name, False) if state is None else state

    def status(self, channel: str) -> ChannelStatus:
        """Setpoint, measured power, emission, interlock and faults of one channel."""
        ch = self._channel(channel)
        self._require_open()
        interlock_ok, faults = self._read_health(ch)
        return ChannelStatus(
            name=ch.name, wavelength_nm=ch.wavelength_nm, setpoint_w=self._read_setpoint(ch),
            measured_w=self._read_measured(ch), emission=self.emission(ch.name), interlock_ok=interlock_ok,
            faults=faults,
        )

    def all_off(self) -> None:
        """Emission off on every channel (read back); tries all of them, then raises the first error."""
        self._require_open()
        try_each(self._switch_off, self.config.channels)

    def restore_setpoints(self, who: str) -> list[str]:
        """Each channel's setpoint back to the profile's where it holds another (`who` chose it: a run's automatic
        exposure, the console; the next `laser on` must not surprise). Every channel is tried; returns one line per
        channel set back or that could not be."""
        lines = []
        for channel in self.config.channels:
            target = channel.setpoint_mw * 1e-3
            try:
                held = self.setpoint_w(channel.name)
                if not math.isclose(held, target, rel_tol=1e-3, abs_tol=1e-9):
                    self.set_power(channel.name, target)
                    lines.append(f"{channel.name} setpoint back to the profile's {format_power(target)} ({who} left "
                                 f"{format_power(held)})")
            except BenchctlError as exc:
                lines.append(f"{channel.name}: could not set the setpoint back to the profile's "
                             f"{format_power(target)}: {exc}")
        return lines

    # -- shared helpers for drivers ----------------------------------------------------------------------------

    def _link(self, channel: LaserChannel) -> SerialLink:
        return self._links[self.config.port_of(channel)]

    def _shares_port(self, channel: LaserChannel) -> bool:
        """Whether other channels are reached through `channel`'s port (so commands must address the channel)."""
        return len(self._ports[self.config.port_of(channel)]) > 1

    def _where(self, channel: LaserChannel) -> str:
        return f"laser channel {channel.name!r} ({self.config.port_of(channel)})"

    def _query(self, channel: LaserChannel, command: str) -> str:
        """Send a query on the channel's port and return its reply (dialects with extra framing override)."""
        return self._link(channel).query(command)

    def _command(self, channel: LaserChannel, command: str) -> None:
        """Send a setting on the channel's port and expect the OK reply."""
        self._link(channel).command(command, self.ok_reply)

    def _query_number(self, channel: LaserChannel, command: str) -> float:
        reply = self._query(channel, command)
        try:
            value = float(reply)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise DeviceError(f"{self._link(channel).where}: expected a number in reply to {command!r}, got {reply!r}")
        return value

    def _query_flag(self, channel: LaserChannel, command: str) -> bool:
        reply = self._query(channel, command)
        flags = {"1": True, "0": False, "ON": True, "OFF": False}
        if reply.strip().upper() not in flags:
            where = self._link(channel).where
            raise DeviceError(f"{where}: expected 1/0 or ON/OFF in reply to {command!r}, got {reply!r}")
        return flags[reply.strip().upper()]

    # -- hooks -------------------------------------------------------------------------------------------------

    def _prepare(self, channel: LaserChannel) -> None:  # noqa: B027 (an optional hook, not abstract)
        """Dialect set-up on connect, before emission is forced off (e.g. autostart off). Default: nothing."""

    def _read_limit_w(self, channel: LaserChannel) -> float | None:
        """The head's own maximum power (W), or None where the dialect cannot tell. Default: None."""
        return None

    def _setpoint_step_w(self, channel: LaserChannel) -> float:
        """The coarsest step the device sets power in (W): a read-back within half a step of the request is the
        request. Default 0: the tolerances above cover the rounding of dialects that take watts or milliwatts."""
        return 0.0

    @abstractmethod
    def _identify(self, channel: LaserChannel) -> str:
        """Identity of the unit or head on `channel`'s port."""

    @abstractmethod
    def _write_power(self, channel: LaserChannel, watts: float) -> None:
        """Send the setpoint command."""

    @abstractmethod
    def _read_setpoint(self, channel: LaserChannel) -> float:
        """The setpoint the device holds (W)."""

    @abstractmethod
    def _read_measured(self, channel: LaserChannel) -> float | None:
        """Measured output power (W), or None where the dialect has no such query."""

    @abstractmethod
    def _write_emission(self, channel: LaserChannel, on: bool) -> None:
        """Send the emission on/off command."""

    @abstractmethod
    def _read_emission(self, channel: LaserChannel) -> bool | None:
        """Emission as the device reports it, or None where the dialect has no such query."""

    @abstractmethod
    def _read_health(self, channel: LaserChannel) -> tuple[bool | None, tuple[str, ...]]:
        """(interlock closed? or None if unknown, active faults other than the interlock)."""

    # -- internals ---------------------------------------------------------------------------------------------

    def _channel(self, name: str) -> LaserChannel:
        try:
            return self._channels[name]
        except KeyError:
            raise BenchctlError(f"no laser channel {name!r}; known channels: {', '.join(self._channels)}") from None

    def _require_open(self) -> None:
        if not self.is_open:
            raise DeviceError(f"{self.config.driver} laser: not connected (use open() or a with block)")

    def _require_writable(self) -> None:
        self._require_open()
        if self.observe:
            raise DeviceError(
                f"{self.config.driver} laser: connected to observe only; reconnect without observe to change it"
            )

    def _switch_off(self, channel: LaserChannel) -> None:
        """Emission off, read back; EmissionNotOff unless the device confirms it (or cannot report emission)."""
        try:
            self._write_emission(channel, False)
            self._emission_commanded[channel.name] = False
            still_on = self._read_emission(channel)
        except DeviceError as exc:
            raise EmissionNotOff(f"{exc}; {self._where(channel)}: {UNKNOWN_EMISSION}") from exc
        if still_on:
            raise EmissionNotOff(f"{self._where(channel)}: emission still ON after the off command: use the key "
                                 "switch / interlock")


def port_lock(url: str) -> DeviceLock:
    """The lock of the laser on port `url`: held while a Laser is connected through it."""
    return DeviceLock(f"laser:{url}", f"laser ({url})")


def try_each(action: Callable[[T], object], items: Iterable[T]) -> None:
    """Run `action` on every item even if some fail (Ctrl-C included), then raise the first failure: one
    channel that does not answer must not stop the others from being switched off."""
    first: BaseException | None = None
    for item in items:
        try:
            action(item)
        except BaseException as exc:
            first = first or exc
    if first is not None:
        raise first
