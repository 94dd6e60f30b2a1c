"""The console's focus panel at the endpoint level, on the small simulated bench with its camera on a simulated Zaber
stage: moves by steps and home, the live view going on while the stage moves, the sharpness of a region (the focus
calibration's measure) falling out of focus and rising again, and `go` to a depth once a focus calibration exists."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import BENCH_PROFILE
from console_bench import ORIGIN, TOKEN, access, call, make_console

from benchctl.calibration.store import Calibration
from benchctl.capture.focus import FocusMap, sharpness
from benchctl.console import app
from benchctl.console.core import Console
from benchctl.console.slm import parse_pattern
from benchctl.devices.sim.focus_mechanics import Mechanism
from benchctl.errors import BadValueError, BenchctlError
from benchctl.profiles import Profile, load_profile

# The stage moves the camera's focus plane 5 um per microstep; at power-on it is at the target plane (20 mm), 2000
# microsteps above home, so home is 10 mm short of focus. At `speed` microsteps a second (the live-view test's 1000: a
# move of 2000 takes 2 s).
FOCUS = """
[focus]
driver = "zaber"
port = "sim://focus-stage?dialect=zaber&speed={speed}"
settle_ms = 0

[sim.focus]
mm_per_step = 5e-3
range_steps = 4000
start_steps = 2000
backlash_steps = 20
"""


def focus_bench(tmp_path: Path, speed: int) -> Profile:
    path = tmp_path / "focus-bench.toml"
    path.write_text(BENCH_PROFILE + FOCUS.format(speed=speed))
    return load_profile(path)


@pytest.fixture
def focus_profile(tmp_path: Path) -> Profile:
    return focus_bench(tmp_path, 200000)


@contextlib.contextmanager
def started(profile: Profile, tmp_path: Path) -> Iterator[Console]:
    console = make_console(profile, tmp_path)
    console.keep_previewing = True
    try:
        yield console
    finally:
        console.close()


@pytest.fixture
def console(focus_profile: Profile, tmp_path: Path) -> Iterator[Console]:
    with started(focus_profile, tmp_path) as console:
        yield console


def frame_after(console: Console, seq: int) -> dict[str, Any]:
    """The header of the first refined frame (not the progressive view's coarse first one) rendered wholly after
    frame `seq`."""
    deadline = time.monotonic() + 30
    while (console.latest is None or console.latest.seq <= seq + 1
           or console.latest.header["source"].get("coarse")):
        assert time.monotonic() < deadline, "no new live-view frame within 30 s"
        time.sleep(0.02)
    return console.latest.header


def test_the_region_sharpness_is_the_calibrations_measure() -> None:
    """The live view's number is capture.focus.sharpness of the region's linear light, colours summed."""
    from benchctl.console.preview import Linear, region_sharpness

    rng = np.random.default_rng(3)
    rgb = rng.random((64, 96, 3)).astype(np.float32) * 0.1
    rgb[20:24, 40:44, 1] += 0.8  # a focused spot inside the region
    image = Linear(rgb, np.zeros((64, 96), bool), None, None)
    measured = region_sharpness(image, (0.25, 0.25, 0.75, 0.75))
    assert measured["pixels"] == [32, 48]
    assert measured["value"] == round(sharpness(rgb[16:48, 24:72].sum(axis=2)), 4)
    assert region_sharpness(image, (0.5, 0.5, 0.52, 0.52))["value"] is None  # 1 x 2 pixels: too few to judge


@pytest.mark.slow
def test_focus_by_steps_with_the_live_view_going_on(tmp_path: Path) -> None:
    with started(focus_bench(tmp_path, 1000), tmp_path) as console:
        focus_by_steps(console)


def focus_by_steps(console: Console) -> None:
    console.show(parse_pattern({"kind": "dots", "channel": "green"}))  # the focus calibration's target
    call(app.power, console, {"power": "20mW"}, channel="green")
    call(app.emission, console, {"on": True}, channel="green")
    call(app.view, console, {"region": [0.1, 0.1, 0.9, 0.9]})
    focused = frame_after(console, console.latest.seq if console.latest else 0)
    assert focused["sharpness"]["region"] == [0.1, 0.1, 0.9, 0.9] and focused["focus"]["position"] is None
    with pytest.raises(BenchctlError, match="no reference position"):  # the stage: home it first
        call(app.focus_move, console, {"steps": 100})

    homed = call(app.focus_home, console)
    assert homed["position"] == 0 and homed["reported"] == 0 and "believed position 0" in homed["moved"]
    blurred = frame_after(console, console.latest.seq)
    assert blurred["focus"]["position"] == 0 and Mechanism(console.profile.sim.focus, 20.0).plane_m == \
        pytest.approx(0.010)  # 10 mm short of the target plane

    headers: list[dict[str, Any]] = []
    mover = threading.Thread(target=lambda: headers.append(call(app.focus_move, console, {"steps": 2000})))
    mover.start()
    seen = []
    while mover.is_alive():  # the live view goes on while the stage moves (2 s)
        seen.append(console.latest.header["focus"]["moving"] if console.latest else None)
        time.sleep(0.05)
    mover.join()
    assert "move +2000" in seen
    assert headers[0]["position"] == 2000 and headers[0]["reported"] == 2000
    refocused = frame_after(console, console.latest.seq)
    assert refocused["focus"] == {"moving": None, "position": 2000, "unit": "microstep", "depth_mm": {}}
    # the dots blur 10 mm out of focus and sharpen again at the target plane
    values = [header["sharpness"]["value"] for header in (focused, blurred, refocused)]
    assert values[1] < 0.9 * values[0] and values[1] < 0.9 * values[2], values
    state = call(app.state, console)["focus"]
    assert state["position"] == 2000 and state["connected"] and state["calibrated"] == {}
    assert state["last"] == "moved +2000 microstep(s); believed position 2000 microstep(s); the device reports 2000"
    call(app.all_off, console)


def test_focus_go_needs_the_calibration_then_arrives_from_its_side(console: Console, focus_profile: Profile) -> None:
    with pytest.raises(BenchctlError, match="no focus calibration for this profile"):
        call(app.focus_go, console, {"depth": "20mm"})
    # a focus calibration stored while the console runs (as a procedure would): depth = 10 mm + 5 um per step
    found = FocusMap.fit([(0, 10.0), (1000, 15.0), (2000, 20.0)], approach=1, backlash_steps=20,
                         repeatability_steps=1.0, range_steps=(0, 4000))
    Calibration.store(focus_profile).save_focus("green", {**found.to_dict(), "unit": "microstep"})
    console.follow_calibration()  # what the status thread does twice a second
    assert call(app.state, console)["focus"]["calibrated"] == {"green": [10.0, 30.0]}

    went = call(app.focus_go, console, {"depth": "22.5mm", "channel": "green"})  # not homed: homes first
    assert went["position"] == 2500 and went["reported"] == 2500 and went["depth_mm"] == {"green": 22.5}
    assert went["moved"].startswith("green at 22.5 mm from the SLM is 2500 microstep(s)")
    went = call(app.focus_go, console, {"depth": "50D"})  # 1 / 50 D = 20 mm; green, the only one calibrated
    # it has to come back down: first 2 x 20 steps past, then up to the position, as the calibration was measured
    assert went["position"] == 2000 and went["reported"] == 2000 and went["approached_from"] == "below"
    with pytest.raises(BenchctlError, match="outside what the focus calibration covers"):
        call(app.focus_go, console, {"depth": "31mm"})
    with pytest.raises(BenchctlError, match="colour 'red' is not focus-calibrated"):
        call(app.focus_go, console, {"depth": "20mm", "channel": "red"})
    with pytest.raises(BadValueError, match='give the depth as {"depth": "70.5mm"'):
        call(app.focus_go, console, {"depth": 20})
    with pytest.raises(BadValueError, match=r'give the move as {"steps": 200} .*got 1.5'):
        call(app.focus_move, console, {"steps": 1.5})
    assert call(app.state, console)["focus"]["position"] == 2000  # nothing moved
    shifted = FocusMap.fit([(0, 11.0), (1000, 16.0), (2000, 21.0)], approach=1, backlash_steps=20,
                           repeatability_steps=1.0, range_steps=(0, 4000))  # measured again, 1 mm further
    Calibration.store(focus_profile).save_focus("green", {**shifted.to_dict(), "unit": "microstep"})
    console.follow_calibration()
    assert call(app.state, console)["focus"]["depth_mm"] == {"green": 21.0}  # the same position, the new map


def test_a_procedure_takes_the_focus_and_gives_it_back(console: Console) -> None:
    console._release_for_run(["laser", "slm", "camera", "focus"])
    assert not console.focus.held.connected
    console.procedures._process = type("Running", (), {"poll": lambda self: None})()  # as while a run goes on
    try:
        with pytest.raises(BenchctlError, match="a procedure holds the focus"):
            call(app.focus_home, console)
    finally:
        console.procedures._process = None
    console._reconnect()
    assert console.focus.held.connected and console.camera.connected


@pytest.mark.slow
def test_an_eos_lens_is_driven_through_the_consoles_own_camera(tmp_path: Path) -> None:
    """The EOS body is opened once, by the console's camera; its lens moves through it, and through the new one
    after the camera was lost and connected again (the position then unknown: a new session counts anew)."""
    with started(load_profile("simulated-eos"), tmp_path) as console:
        assert console.focus.held.device.camera is console.camera.device
        call(app.focus_home, console)
        moved = call(app.focus_move, console, {"steps": 5})
        assert moved["position"] == 5 and moved["reported"] is None and moved["unit"] == "drive"
        console.camera.lost("cable pulled")
        assert call(app.connect, console, {"device": "camera"}) == {"connected": True, "error": None}
        assert console.focus.held.device.camera is console.camera.device and console.focus.status["position"] is None
        assert call(app.focus_move, console, {"steps": 2})["position"] is None  # moves, but from nowhere known


@pytest.mark.parametrize("headers", [
    {"x-benchctl-token": "not-the-token", "origin": ORIGIN},
    {"x-benchctl-token": TOKEN},  # no Origin: a request that moves a device must carry the page's
    {"x-benchctl-token": TOKEN, "origin": "http://evil.example"},
])
def test_refused_focus_requests_move_nothing(console: Console, headers: dict[str, str]) -> None:
    from starlette.testclient import TestClient

    call(app.focus_home, console)
    with TestClient(app.create_app(console, access()), base_url=ORIGIN) as client:
        for path, body in (("/api/focus/move", {"steps": 500}), ("/api/focus/home", {}),
                           ("/api/focus/go", {"depth": "20mm"})):
            refused = client.post(path, json=body, headers=headers)
            assert refused.status_code == 403 and refused.text.startswith("refused: "), path
        assert console.focus.held.device.status()["reported"] == 0  # the stage itself did not move
        moved = client.post("/api/focus/move", json={"steps": 500}, headers={"x-benchctl-token": TOKEN,
                                                                              "origin": ORIGIN})
        assert moved.status_code == 200 and moved.json()["reported"] == 500
