"""Shared fixtures: a small simulated bench so end-to-end tests run in seconds on a CPU."""

from __future__ import annotations

import copy
import itertools
import json
import numbers
import os
import re
import sys
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

from device_skips import pytest_configure, pytest_runtest_makereport  # noqa: F401 - the plugin's hooks, for pytest

from benchctl.capture.raw import RawImage, decode_raw
from benchctl.cli import main
from benchctl.devices.sim import physics
from benchctl.dng import CFA_LAYOUTS, dng_bytes
from benchctl.profiles import Profile, load_profile

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

SMALL_PROFILE = """\
name = "small"
description = "scaled-down simulated bench for tests"

[optics]
distance_mm = 20.0
roi = [48, 80]

[slm]
width = 96
height = 64
pitch_um = 8.0
bit_depth = 8

[laser]
driver = "template"
port = "sim://rgb-laser"

[laser.protocol]
set_power = "CH{channel}:POW {mw:.2f}"
get_power = "CH{channel}:POW?"
get_measured = "CH{channel}:MEAS?"
enable = "CH{channel}:EMIT 1"
disable = "CH{channel}:EMIT 0"
get_emission = "CH{channel}:EMIT?"
get_status = "CH{channel}:STAT?"
identify = "*IDN?"

[[laser.channels]]
name = "red"
index = 1
wavelength_nm = 680
max_power_mw = 40
setpoint_mw = 40

[[laser.channels]]
name = "green"
index = 2
wavelength_nm = 520
max_power_mw = 40
setpoint_mw = 2

[[laser.channels]]
name = "blue"
index = 3
wavelength_nm = 450
max_power_mw = 40
setpoint_mw = 2
"""


# A simulated bench big enough for a dot-grid registration, small enough that a full procedure takes seconds:
# a 128 x 192 SLM imaged at 2 sensor pixels per SLM pixel, turned 1.5 degrees, onto a 300 x 440 sensor.
BENCH_PROFILE = SMALL_PROFILE.replace('name = "small"', 'name = "bench"').replace("""[optics]
distance_mm = 20.0
roi = [48, 80]

[slm]
width = 96
height = 64
""", """[optics]
distance_mm = 20.0
roi = [96, 160]
iris_fraction = 0.5

[slm]
width = 192
height = 128
settle_ms = 0
""").replace('port = "sim://rgb-laser"', 'port = "sim://rgb-laser"\ntimeout_s = 0.3') + """
[camera]
driver = "sim"

[sim.beam]
efficiency = 4e-6

[sim.imaging]
magnification = 1.0
rotation_deg = 1.5
offset_px = [3.0, -5.0]

[sim.sensor]
shape = [300, 440]
margin = [8, 12]
pixel_um = 4.0
"""


@pytest.fixture
def bench_profile_path(tmp_path: Path) -> Path:
    """A complete simulated bench (laser, SLM, camera) for procedures: 128 x 192 SLM, ROI 96 x 160, 8 um, 20 mm."""
    path = tmp_path / "bench.toml"
    path.write_text(BENCH_PROFILE)
    return path


@pytest.fixture
def small_profile_path(tmp_path: Path) -> Path:
    """A valid profile for a 64 x 96 SLM grid (ROI 48 x 80), 8 um pitch, 20 mm."""
    path = tmp_path / "small.toml"
    path.write_text(SMALL_PROFILE)
    return path


# -- variants of the simulated bench -------------------------------------------------------------------------------

# SMALL_PROFILE's 64 x 96 SLM grid (ROI 48 x 80, 8 um) on BENCH_PROFILE's simulated bench, a layer for
# bench_profile_text: its image lands 6 rows below and 15 columns left of the centre of a 176 x 256 sensor with
# 4 / 10 masked rows / columns; magnification and rotation stay BENCH_PROFILE's unless a test sets its own.
SMALL_BENCH: dict[str, Any] = {
    "optics": {"roi": [48, 80]},
    "slm": {"width": 96, "height": 64},
    "sim": {"beam": {"efficiency": 1e-5}, "imaging": {"offset_px": [6.0, -15.0]},
            "sensor": {"shape": [176, 256], "margin": [4, 10]}},
}


def bench_profile_text(*layers: Mapping[str, Any], setpoints_mw: Mapping[str, float] | None = None,
                       **overrides: Any) -> str:
    """BENCH_PROFILE changed by each of `layers` (dicts such as SMALL_BENCH) in turn, then by `overrides`, as TOML.

    A change names a top-level key or section ("name", "optics", "slm", "laser", "camera", "sim"): a dict is merged
    into the section key by key, sub-sections included (sim={"imaging": {"rotation_deg": 3.0}} changes only that
    key of [sim.imaging]); any other value replaces the key; None removes the key or section. `setpoints_mw` sets
    laser channels' setpoints by channel name.
    """
    data = tomllib.loads(BENCH_PROFILE)
    for layer in (*layers, overrides):
        data = _merged(data, layer)
    channels = {channel["name"]: channel for channel in data["laser"]["channels"]}
    for name, mw in (setpoints_mw or {}).items():
        channels[name]["setpoint_mw"] = mw
    return _toml_table(data)


@pytest.fixture
def make_bench_profile(tmp_path: Path) -> Callable[..., Profile]:
    """Factory: make_bench_profile(*layers, setpoints_mw=..., **overrides) writes bench_profile_text(...) to a new
    file under tmp_path and returns it loaded."""
    file_numbers = itertools.count(1)

    def make(*layers: Mapping[str, Any], **changes: Any) -> Profile:
        path = tmp_path / f"bench-{next(file_numbers)}.toml"
        path.write_text(bench_profile_text(*layers, **changes))
        return load_profile(path)

    return make


def truly_registered(profile: Profile, *colours: str) -> Profile:
    """`profile` with the simulated bench's true camera registration stored for `colours` (default: green)."""
    from benchctl.calibration.store import Calibration

    store = Calibration.store(profile)
    for colour in colours or ("green",):
        store.save_registration(colour, {"homography": physics.camera_homography(profile).tolist(), "rms_px": 0.0})
    return profile


def truly_focused(profile: Profile, *colours: str) -> Profile:
    """`profile` with the simulated focus mechanism's true map stored as its focus calibration for `colours` (default:
    green): a Zaber stage homed, then approached from below, lags its counter by the backlash, so position s focuses
    at plane + mm_per_step (s - backlash - start_steps) (`benchctl.devices.sim.focus_mechanics`)."""
    from benchctl.calibration.store import Calibration
    from benchctl.capture.focus import FocusMap

    mechanics, distance = profile.sim.focus, profile.section("optics").distance_mm
    plane = mechanics.plane_mm if mechanics.plane_mm is not None else distance
    slope = mechanics.mm_per_step
    found = FocusMap((plane - slope * (mechanics.backlash_steps + mechanics.start_steps), slope), 1,
                     mechanics.backlash_steps, 0.0, (0.0, float(mechanics.range_steps)), 0.0)
    store = Calibration.store(profile)
    for colour in colours or ("green",):
        store.save_focus(colour, {**found.to_dict(), "unit": "microstep"})
    return profile


def one_error_line(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """Run benchctl; it must exit 2 with exactly one error line (no traceback). Returns that line."""
    assert main(argv) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("benchctl: error: ")
    return line


def sim_exposure(profile: Profile, gray: np.ndarray | None, powers_w: dict[str, float], frame: int = 1) -> RawImage:
    """One simulated exposure (10 ms, ISO 100) of `gray` (None: the SLM shows nothing) lit by `powers_w`, written as
    a DNG and decoded. Each frame number has its own noise."""
    sensor = profile.sim.sensor
    mosaic = physics.render_mosaic(profile, gray, powers_w, exposure_s=0.01, iso=100, frame=frame)
    return decode_raw(dng_bytes(mosaic, cfa=sensor.cfa, black_level=sensor.black_level,
                                white_level=sensor.white_level, active_area=sensor.active_area))


def mono_exposure(profile: Profile, gray: np.ndarray | None, powers_w: dict[str, float], frame: int = 1,
                  colour: int = 1) -> RawImage:
    """`sim_exposure` by a monochrome sensor lit by one colour (plane index `colour`; no light: dark), written as a
    monochrome DNG and decoded. Made from the simulator's renders with each of the four Bayer layouts: every pixel
    is taken from a render in which its site carries that colour's filter, so the sensor responds to the colour
    alike at every pixel (the filter's response; a flat mono response differs by a gain the merge's balance takes)."""
    sensor = profile.sim.sensor
    mono = np.zeros(sensor.shape, dtype=np.uint16)
    filled = np.zeros(sensor.shape, dtype=bool)
    site = np.indices(sensor.shape) % 2  # the margins are even: the full sensor's sites are the active area's
    for layout, cells in CFA_LAYOUTS.items():
        with_layout = msgspec.structs.replace(profile, sim=msgspec.structs.replace(
            profile.sim, sensor=msgspec.structs.replace(sensor, cfa=layout)))
        mosaic = physics.render_mosaic(with_layout, gray, powers_w, exposure_s=0.01, iso=100, frame=frame)
        take = (np.reshape(cells, (2, 2))[site[0], site[1]] == colour) & ~filled
        mono[take], filled[take] = mosaic[take], True
    return decode_raw(dng_bytes(mono, cfa=None, black_level=sensor.black_level, white_level=sensor.white_level,
                                active_area=sensor.active_area))


def _merged(base: Mapping[str, Any], changes: Mapping[str, Any]) -> dict[str, Any]:
    """`base` with `changes` merged in (see bench_profile_text); neither is modified."""
    out = dict(base)
    for key, value in changes.items():
        if value is None:
            if key not in out:
                raise KeyError(f"cannot remove {key!r}: the profile has no such key (it has {', '.join(out)})")
            del out[key]
        elif isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = _merged(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def _toml_table(table: Mapping[str, Any], where: str = "") -> str:
    """The keys of `table` as TOML lines, then each sub-table and array of tables under its own header."""

    def is_table_array(value: Any) -> bool:
        return isinstance(value, list) and bool(value) and all(isinstance(item, Mapping) for item in value)

    text = "".join(f"{_toml_key(key)} = {_toml_value(value)}\n" for key, value in table.items()
                   if not isinstance(value, Mapping) and not is_table_array(value))
    for key, value in table.items():
        name = f"{where}.{_toml_key(key)}" if where else _toml_key(key)
        if isinstance(value, Mapping):
            text += f"\n[{name}]\n" + _toml_table(value, name)
        elif is_table_array(value):
            text += "".join(f"\n[[{name}]]\n" + _toml_table(item, name) for item in value)
    return text


def _toml_key(key: str) -> str:
    return key if re.fullmatch(r"[A-Za-z0-9_-]+", key) else json.dumps(key)


def _toml_value(value: Any) -> str:
    """A TOML literal: JSON's escapes are valid in TOML's basic strings."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        return repr(float(value))
    if isinstance(value, (str, Path)):
        return json.dumps(str(value))
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    raise TypeError(f"no TOML literal for {value!r} ({type(value).__name__})")


@pytest.fixture(autouse=True)
def sim_state_dir(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Each test gets its own simulated-bench state folder, so tests never see each other's (or a user's) state."""
    folder = tmp_path_factory.mktemp("sim-state")
    monkeypatch.setenv("BENCHCTL_SIM_DIR", str(folder))
    return folder


@pytest.fixture(autouse=True)
def calibration_and_cache_dirs(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Each test gets empty calibration and hologram-cache folders (never the user's)."""
    folder = tmp_path_factory.mktemp("calibration")
    monkeypatch.setenv("BENCHCTL_CALIBRATION_DIR", str(folder / "calibration"))
    monkeypatch.setenv("BENCHCTL_CACHE_DIR", str(folder / "cache"))
    return folder


@pytest.fixture(autouse=True)
def aravis_fake_interface_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """Aravis scans only its in-process fake camera: GigE Vision discovery would broadcast on every network
    interface (the GigE Vision tests run in a network namespace of their own)."""
    monkeypatch.setenv("BENCHCTL_ARAVIS_INTERFACES", "Fake")


@pytest.fixture(autouse=True)
def lock_dir(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Each test gets its own device-lock folder (never the user's locks)."""
    folder = tmp_path_factory.mktemp("locks")
    monkeypatch.setenv("BENCHCTL_LOCK_DIR", str(folder))
    return folder


# -- the quick loop stays quick -----------------------------------------------------------------------------------
# `pytest -m "not slow"` is the loop a developer runs after each change: a test that takes longer than SLOW_S of
# wall time belongs to the slow set. Every unmarked test over it is listed at the end; with
# BENCHCTL_TEST_TIMES=strict (what `.ci/run` sets) it fails the session; a test still running after
# STILL_RUNNING_S is named on the terminal as it runs.
SLOW_S = 5.0
STILL_RUNNING_S = 30.0
_unmarked_slow: list[tuple[str, float]] = []
_still_running: dict[str, threading.Timer] = {}


def pytest_runtest_logstart(nodeid: str, location: tuple[str, int | None, str]) -> None:
    def say() -> None:
        sys.__stderr__.write(f"\n[still running after {STILL_RUNNING_S:.0f} s: {nodeid}]\n")
        sys.__stderr__.flush()

    timer = threading.Timer(STILL_RUNNING_S, say)
    timer.daemon = True
    timer.start()
    _still_running[nodeid] = timer


def pytest_runtest_logfinish(nodeid: str, location: tuple[str, int | None, str]) -> None:
    timer = _still_running.pop(nodeid, None)
    if timer is not None:
        timer.cancel()


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.when == "call" and report.duration > SLOW_S and "slow" not in report.keywords:
        _unmarked_slow.append((report.nodeid, report.duration))


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if not _unmarked_slow:
        return
    lines = "\n".join(f"  {seconds:5.1f} s  {nodeid}" for nodeid, seconds in sorted(_unmarked_slow))
    sys.__stderr__.write(f"\n{len(_unmarked_slow)} test(s) not marked slow took over {SLOW_S:g} s (mark them "
                         f"@pytest.mark.slow, or make them quicker):\n{lines}\n")
    if os.environ.get("BENCHCTL_TEST_TIMES") == "strict":
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
