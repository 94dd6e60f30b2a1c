"""What `benchctl laser`, `benchctl slm` and `benchctl sim` do: open the profile's device, act, report.

Every function returns the lines to print, so the command line stays a thin layer and tests can call these
directly. Emission safety lives in the laser driver (off at connect and on close); this module only decides
how long emission stays on.
"""

from __future__ import annotations

import glob
import math
import os
import re
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable
from urllib.parse import urlsplit

import numpy as np

from benchctl.devices.errors import EmissionNotOff
from benchctl.devices.laser import ChannelStatus, open_laser
from benchctl.devices.laser.base import UNKNOWN_EMISSION, port_lock
from benchctl.devices.power import format_power
from benchctl.devices.safety import wait
from benchctl.devices.sim.laser_emulators import parse_faults
from benchctl.devices.sim.state import list_states, load_state, reset_states, save_state, state_dir
from benchctl.errors import BenchctlError
from benchctl.profiles import Profile

if TYPE_CHECKING:
    from benchctl.devices.camera import Camera
    from benchctl.devices.slm import SLM

_DURATION = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*(ms|s|min|m|h)?\s*$")
_SECONDS = {"ms": 1e-3, "s": 1.0, None: 1.0, "min": 60.0, "m": 60.0, "h": 3600.0}
CAMERA = "sim-camera"  # the simulated camera's name in the simulated bench's state (devices.sim.physics)
HOLDER_EXIT_S = 15.0  # how long `laser off` waits for a command holding the laser to switch it off and exit


def parse_duration(text: str) -> float:
    """'30s', '500ms', '2m', '1.5' (seconds) -> seconds."""
    match = _DURATION.match(text)
    if not match:
        raise BenchctlError(f"duration {text!r} not understood; use e.g. 30s, 500ms, 2m")
    return float(match.group(1)) * _SECONDS[match.group(2)]


def _status_line(s: ChannelStatus) -> str:
    measured = format_power(s.measured_w) if s.measured_w is not None else "n/a"
    interlock = {True: "closed", False: "OPEN", None: "n/a"}[s.interlock_ok]
    faults = ", ".join(s.faults) or "none"
    return (f"{s.name:<8} {s.wavelength_nm:>6g} nm  setpoint {format_power(s.setpoint_w):>10}  measured "
            f"{measured:>10}  emission {'ON' if s.emission else 'off':<3}  interlock {interlock:<6}  faults {faults}")


def laser_status(profile: Profile) -> list[str]:
    """Identity and one line per channel: wavelength, setpoint, measured power, emission, interlock, faults."""
    with open_laser(profile.section("laser"), observe=True) as laser:
        return [f"laser: {laser.identity()}"] + [_status_line(laser.status(name)) for name in laser.channel_names]


def laser_set(profile: Profile, channel: str, power: str) -> list[str]:
    """Change one channel's setpoint (emission stays off); the device's read-back value is reported."""
    with open_laser(profile.section("laser")) as laser:
        watts = laser.set_power(channel, power)
        return laser.connect_report() + [f"{channel}: setpoint {format_power(watts)} (read back)"]


def laser_on(profile: Profile, channel: str, duration_s: float | None, leave_on: bool,
             out: Callable[[str], None] = print, sleep: Callable[[float], None] = wait) -> list[str]:
    """Emission on `channel` for `duration_s` (None: until Ctrl-C), then off unless `leave_on`."""
    try:
        with open_laser(profile.section("laser")) as laser:
            for line in laser.connect_report():
                out(line)
            laser.set_emission(channel, True)
            setpoint = laser.setpoint_w(channel)
            emits = f"at {_emitted(setpoint, laser.measured_w(channel), profile.channel(channel).setpoint_mw * 1e-3)}"
            if setpoint <= 0:
                out(f"{channel}: the setpoint is 0 mW, so no light comes out; set one with "
                    f"`benchctl laser set {channel} 5mW`")
            if leave_on:
                laser.leave_on = True
                return [f"{channel}: emission ON {emits} and LEFT ON after exit; `benchctl laser off {channel}` turns "
                        "it off"]
            out(f"{channel}: emission ON {emits} "
                + (f"for {duration_s:g} s" if duration_s is not None else "until Ctrl-C"))
            while duration_s is None:
                sleep(3600)
            sleep(duration_s)
            laser.set_emission(channel, False)
    except KeyboardInterrupt:
        out(f"{channel}: interrupted; emission off on every channel")  # close() has run by now
        raise
    return [f"{channel}: emission off"]


def _emitted(setpoint_w: float, measured_w: float | None, profile_w: float) -> str:
    """The power a channel emits at, as read back, and how it compares with the profile's setpoint: '27.4 mW (read
    back; measured 27.3 mW; 13.7x the profile's setpoint of 2 mW)'."""
    notes = ["read back"] + ([f"measured {format_power(measured_w)}"] if measured_w is not None else [])
    if not math.isclose(setpoint_w, profile_w, rel_tol=1e-3, abs_tol=1e-9):
        ratio = f"{setpoint_w / profile_w:.3g}x" if setpoint_w > 0 and profile_w > 0 else "not"
        notes.append(f"{ratio} the profile's setpoint of {format_power(profile_w)}")
    return f"{format_power(setpoint_w)} ({'; '.join(notes)})"


def sim_fault(device: str, faults: list[str], clear: bool, profile: Profile) -> list[str]:
    """Set (or clear) the faults a simulated device shows from its next connection on. The device is the
    simulated camera, a sim:// laser or focus stage of `profile` or one with saved state; unknown faults are
    refused."""
    ports = [urlsplit(profile.laser.port_of(ch)) for ch in profile.laser.channels] if profile.laser else []
    lasers = {port.netloc for port in ports if port.scheme == "sim"}
    lasers |= {name for name, saved in list_states().items() if "channels" in saved}  # connected before
    focus_port = urlsplit(profile.focus.port or "") if profile.focus else None
    stages = {focus_port.netloc} if focus_port is not None and focus_port.scheme == "sim" else set()
    stages |= {name for name, saved in list_states().items() if saved.get("dialect") == "zaber"}
    if device != CAMERA and device not in lasers | stages:
        known = ", ".join(sorted(lasers | stages | {CAMERA}))
        raise BenchctlError(f"no simulated device {device!r} (known: {known})")
    if device == CAMERA:
        from benchctl.devices.sim.camera import unplug_frame

        for fault in faults:
            unplug_frame(fault)
    else:
        from benchctl.devices.sim.zaber_stage import parse_faults as stage_faults

        try:
            (stage_faults if device in stages else parse_faults)(faults)
        except ValueError as exc:
            raise BenchctlError(f"{device}: {exc}") from None
    state = load_state(device)
    state["faults"] = [] if clear else sorted(set(state.get("faults", [])) | set(faults))
    save_state(device, state)
    return [f"{device}: faults {', '.join(state['faults']) or 'none'}"]


def laser_off(profile: Profile, channel: str, wait_s: float = HOLDER_EXIT_S) -> list[str]:
    """Emission off on one channel or on all ('all'); connecting already turns every channel off. A command
    holding the laser (a run, `laser on`) is sent SIGTERM first: it switches emission off and exits."""
    config = profile.section("laser")
    lines = stop_laser_holders(sorted({config.port_of(ch) for ch in config.channels}), wait_s)
    with open_laser(config) as laser:
        names = laser.channel_names if channel == "all" else [channel]
        for name in names:
            laser.set_emission(name, False)
        return lines + laser.connect_report() + [f"{name}: emission off" for name in names]


def stop_laser_holders(ports: list[str], wait_s: float) -> list[str]:
    """SIGTERM to each other process that holds one of the laser `ports`, then wait for it to let go (its
    signal handling switches emission off on the way out). One that does not let go: EmissionNotOff."""
    lines = []
    for url in ports:
        lock = port_lock(url)
        if lock.wait_free(0):
            continue
        holder = lock.holder()
        if holder is None or holder.pid == os.getpid():
            continue  # not (yet) told who holds it, or this process: opening the laser says so
        try:
            os.kill(holder.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass  # it ended meanwhile, and with it its lock
        except PermissionError:
            raise EmissionNotOff(f"laser ({url}) is {holder}, a process of another user that this one may not "
                                 f"stop; {UNKNOWN_EMISSION}") from None
        lines.append(f"laser ({url}) was {holder}: sent it SIGTERM (it switches emission off and exits)")
        if not lock.wait_free(wait_s):
            raise EmissionNotOff(f"laser ({url}): `{holder.command}` (pid {holder.pid}) still holds it "
                                 f"{wait_s:g} s after SIGTERM; {UNKNOWN_EMISSION}")
    return lines


def _open_camera(profile: Profile) -> Camera:
    """The profile's camera, imported here so that laser commands do not load the camera drivers."""
    from benchctl.devices.camera import open_camera

    return open_camera(profile)


def _open_slm(profile: Profile) -> SLM:
    """The profile's SLM with the lookup tables measured for it (calibration/<profile>/, where the profile names
    none), imported here so that laser and camera commands do not load the SLM drivers."""
    from benchctl.calibration.calibrated import Calibrated
    from benchctl.devices.slm import open_slm

    if profile.slm is not None and profile.optics is not None:  # a calibration is stored for an SLM and optics
        profile = Calibrated.stored(profile).profile
    return open_slm(profile.require("slm"))


def human(value: object, key: str = "") -> str:
    """A value for people, not a Python repr: numbers to 6 significant digits (a power, keyed `*_w`, in W, mW or uW),
    yes / no, lists and tables inline ('red linear; green lut-green.csv'), an empty one as 'none'."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return format_power(value) if key.endswith("_w") else f"{value:.6g}"
    if isinstance(value, dict):
        return "; ".join(f"{_label(name)} {human(item, str(name))}" for name, item in value.items()) or "none"
    if isinstance(value, (list, tuple)):
        return ", ".join(human(item, key) for item in value) or "none"
    return "none" if value is None else str(value)


def _human_lines(table: dict[str, Any], indent: str) -> list[str]:
    """`key: value` lines, a table of tables (a laser's channels) as an indented block of its own."""
    lines = []
    for key, value in table.items():
        if isinstance(value, dict) and value and all(isinstance(item, dict) for item in value.values()):
            lines += [f"{indent}{key}:", *_human_lines(value, indent + "  ")]
        else:
            lines.append(f"{indent}{_label(key)}: {human(value, key)}")
    return lines


def _label(key: object) -> str:
    """A key as shown next to its value: a power's unit suffix goes (the value carries its unit)."""
    return str(key).removesuffix("_w")


def slm_info(profile: Profile) -> list[str]:
    """The SLM's driver, geometry, settle time and lookup tables."""
    with _open_slm(profile) as slm:
        return _human_lines(slm.info(), "")


def slm_show(profile: Profile, path: Path, channel: str | None) -> list[str]:
    """Show an image file's gray levels as they are, or a .npy phase (radians) encoded for `channel`."""
    path = Path(path)
    with _open_slm(profile) as slm:
        if path.suffix.lower() == ".npy":
            if channel is None:
                raise BenchctlError(f"{path}: a phase in radians needs --channel to choose the lookup table")
            try:
                phase = np.load(path, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise BenchctlError(f"{path}: cannot read phase array: {exc}") from None
            gray = slm.show_phase(phase, channel)
            return [f"showing {path} as {channel} phase (gray {int(gray.min())}..{int(gray.max())})"]
        if channel is not None:
            raise BenchctlError(f"{path}: --channel applies to .npy phases; an image is shown as its gray levels")
        from benchctl.images import read_image

        image = read_image(path)
        if image.ndim == 3:
            raise BenchctlError(f"{path}: the SLM shows gray levels, this image has {image.shape[2]} channels")
        slm.show_gray(image)
        return [f"showing {path} ({image.shape[1]}x{image.shape[0]}, {image.dtype})"]


def slm_blank(profile: Profile) -> list[str]:
    """Show gray level 0 everywhere."""
    with _open_slm(profile) as slm:
        slm.blank()
    return ["SLM blank"]


def camera_info(profile: Profile) -> list[str]:
    """What the camera says it is, and the capture settings the profile gives."""
    config = profile.section("camera")
    with _open_camera(profile) as camera:
        lines = _human_lines(camera.identity(), "")
    exposure = f"{config.exposure_s:g} s" if config.exposure_s else "as set on the camera"
    writes = "on" if config.write_properties else "off (set exposure, ISO and RAW on the body)"
    return lines + [f"exposure: {exposure}", f"iso: {config.iso or 'as set on the camera'}",
                    f"frames per capture: {config.frames}", f"property writes: {writes}"]


def camera_capture(profile: Profile, output: Path, frames: int | None) -> Iterator[str]:
    """Capture RAW frames: one frame to `output`, several to `output`'s stem numbered -000, -001, ..., one line per
    frame as it arrives. Each file is saved under its numbered name the moment it arrives, never modified, and
    dropped from memory (one frame is held however many are taken); an existing file is never replaced, and the
    disk must have room for every frame (both refused before the first shutter)."""
    output = Path(output)
    numbered = sorted(output.parent.glob(f"{glob.escape(output.stem)}-[0-9][0-9][0-9].*"))
    taken = [output] if output.exists() else numbered or sorted(output.parent.glob(f"{glob.escape(output.name)}.*"))
    if taken:
        raise BenchctlError(f"{taken[0]} exists; captured files never replace one (choose another --output)")
    count = frames or profile.section("camera").frames
    _check_capture_disk(profile, output.parent, count)
    with _open_camera(profile) as camera:
        for frame in camera.captures(output.parent, frames=count, stem=output.stem):
            assert frame.path is not None  # captures saves every frame to the folder it is given
            target = frame.path
            if count == 1:
                target = output if output.suffix else output.with_suffix(frame.suffix)
                try:
                    os.link(frame.path, target)  # never replaces, unlike a rename
                except FileExistsError:
                    raise BenchctlError(f"{target} appeared during the capture and is kept; the frame is "
                                        f"{frame.path}") from None
                frame.path.unlink()
            yield f"captured {target} ({frame.format}, {len(frame.data)} bytes, camera name {frame.file_name})"


def _check_capture_disk(profile: Profile, folder: Path, count: int) -> None:
    """BenchctlError (one line, with the largest count that fits) when `count` frames of the profile's camera, as its
    driver expects them, would not fit on the disk that holds `folder`."""
    from benchctl.devices.camera import frame_size
    from benchctl.memory import size_text
    from benchctl.runner.estimates import free_bytes

    each, free = frame_size(profile).file_bytes, free_bytes(folder)
    if count * each > free:
        raise BenchctlError(f"{folder}: {size_text(free)} free, and {count} frame(s) of about {size_text(each)} need "
                            f"{size_text(count * each)}: at most --frames {free // each} fits here; free some space or "
                            f"capture elsewhere (-o)")


def devices_found() -> list[str]:
    """Serial ports, PTP and GenICam cameras, framebuffers and desktop outputs on this machine; for each kind that
    cannot be looked up, why."""
    from benchctl.devices.discovery import discover  # USB, Aravis, X11 probing: only `devices` needs it

    found = discover()
    return [
        *_section("serial ports", [f"{p.device}  {p.description}  {p.hwid}" for p in found.serial_ports], None),
        *_section("PTP cameras", [f"{c.usb_id}  bus {c.bus} address {c.address}  {c.manufacturer or '?'} "
                                  f"{c.product or '?'}" for c in found.cameras],
                  found.usb_error and f"cannot scan USB: {found.usb_error}"),
        *_section("GenICam cameras (Aravis)", [f"{c.device_id}  {c.vendor} {c.model}  serial {c.serial}  "
                                               f"{c.protocol} {c.address}" for c in found.genicam],
                  found.genicam_error and f"cannot list: {found.genicam_error}"),
        *_section("framebuffers", [f"{f.device}  {f.name or '?'}  {f.width}x{f.height}  {f.bits_per_pixel} bpp"
                                   for f in found.framebuffers], None),
        *_section("desktop outputs (X11)", [output.describe() for output in found.outputs], found.outputs_error),
        *_section("focus (a [focus] driver for each)",
                  [f"{p.device}  {p.description}  (driver zaber)" for p in found.serial_ports
                   if "zaber" in f"{p.description} {p.hwid}".lower()]
                  + [f"the lens of {c.product or 'the camera'} {c.usb_id}  (driver eos, with camera driver ptp)"
                     for c in found.cameras if c.usb_id.startswith("04a9:")], None),
    ]


def _section(title: str, entries: list[str], error: str | None) -> list[str]:
    """`title:`, then each entry indented; where there is none, why (`error`) or "none"."""
    return [f"{title}:", *(f"  {entry}" for entry in entries), *([f"  {error}"] if error else [] if entries
                                                                  else ["  none"])]


def sim_status() -> list[str]:
    """Where the simulated bench keeps its state, and what each simulated device holds."""
    states = list_states()
    lines = [f"simulated bench state: {state_dir()}"]
    if not states:
        return lines + ["  (empty: every simulated device starts from its power-on state)"]
    for name, state in states.items():
        lines += [f"  {name}:", *_human_lines(state, "    ")]
    return lines


def sim_reset() -> list[str]:
    """Forget every simulated device's state (as after a power cycle)."""
    removed = reset_states()
    return [f"removed {len(removed)} file(s) from {state_dir()}"]
