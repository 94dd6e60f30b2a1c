"""A monochrome camera through the capture pipeline: each colour is exposed alone, so its light is read from every
pixel of the mono frame. Registration on the simulated bench with a monochrome sensor made from the simulator's own
renders (conftest.mono_exposure; test_colour_planes captures and scores a colour chart with it), and end to end
through `benchctl run` with Aravis's fake camera in Mono8 (tests/test_display_slm.py runs the colour capture with
the fake camera in Mono16 and the SLM on a real X server)."""

from __future__ import annotations

import json
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import SMALL_BENCH, bench_profile_text, mono_exposure
from gigevision import mono8_ramp
from test_registration import CORNER_TOLERANCE, GEOMETRY, corner_error, dot_grid_capture

from benchctl.calibration.store import Calibration
from benchctl.capture.raw import decode_raw
from benchctl.capture.registration import Registration, dots_in_capture, fit_registration
from benchctl.cli import main
from benchctl.devices.sim import physics
from benchctl.images import read_image
from benchctl.profiles import Profile, load_profile


@pytest.mark.parametrize("channel, colour", [("red", 0), ("blue", 2)])
def test_registration_finds_the_dots_in_a_mono_capture(make_bench_profile: Callable[..., Profile], channel: str,
                                                       colour: int) -> None:
    """test_registration's dot grid, captured by a monochrome sensor: the homography is recovered as closely as
    from a Bayer capture (its tolerance)."""
    profile = make_bench_profile(GEOMETRY)
    image, points = dot_grid_capture(profile, channel, exposure=partial(mono_exposure, colour=colour))
    assert image.monochrome and image.saturation_fraction == 0
    fit = fit_registration(points, dots_in_capture(image, colour))
    assert fit.inliers >= 0.98 * fit.points and fit.scale == pytest.approx(2.0, rel=0.005)
    assert corner_error(profile, fit.homography, physics.camera_homography(profile)) < CORNER_TOLERANCE * 2.0


# -- end to end with Aravis's fake camera ------------------------------------------------------------------------


def store_registration(profile_path: Path, scale: float, offset: tuple[float, float]) -> None:
    """A stored registration for every channel of the profile: target pixel (x, y) lands on sensor pixel
    scale * (x, y) + offset. Aravis's fake camera draws its own pattern whatever the SLM shows, so registration
    cannot be measured on it; a bench measures it once (procedures/registration.toml)."""
    profile = load_profile(profile_path)
    fit = Registration(np.array([[scale, 0.0, offset[0]], [0.0, scale, offset[1]], [0.0, 0.0, 1.0]]), 0.0, 0.0,
                       251, 251)
    for channel in profile.channels:
        Calibration.store(profile).save_registration(channel.name, {**fit.to_dict(), "through_model": False})


CAPTURE_ON_A_FAKE_CAMERA = """name = "colour-capture"
procedure = "colour-capture"

[parameters]
targets = ["chart:bars"]
frames = 1
dark_frames = 0
registration = "stored"
lut_calibration = "skip"
exposure = "auto"
"""


def finished_run(runs: Path) -> tuple[Path, dict[str, Any], list[dict[str, Any]]]:
    """The one run folder under `runs`, its metrics and its finished steps' results (in order)."""
    (folder,) = runs.iterdir()
    assert json.loads((folder / "run.json").read_text())["stop"]["status"] == "finished"
    events = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    return folder, json.loads((folder / "metrics.json").read_text()), [e for e in events if e["event"] == "done"]


def test_colour_capture_runs_on_a_mono8_genicam_camera(tmp_path: Path) -> None:
    """`benchctl run` of the colour capture on a profile whose camera is Aravis's fake camera in Mono8 (64 x 96 SLM
    imaged at 2 sensor pixels per SLM pixel onto a 256 x 192 region): automatic exposure, capture, registration
    onto the target, merge and scores all read every colour from the mono frames."""
    profile = tmp_path / "mono.toml"
    profile.write_text(bench_profile_text(SMALL_BENCH, camera={
        "driver": "genicam", "serial": "1", "pixel_format": "Mono8", "region": [0, 0, 256, 192], "exposure_s": 0.01,
        "gain": 0.0}))
    store_registration(profile, 2.0, (32.5, 32.5))
    procedure = tmp_path / "capture.toml"
    procedure.write_text(CAPTURE_ON_A_FAKE_CAMERA)
    assert main(["run", str(procedure), "--profile", str(profile), "--out", str(tmp_path / "runs")]) == 0
    folder, metrics, done = finished_run(tmp_path / "runs")
    assert json.loads((folder / "devices.json").read_text())["camera"]["pixel_format"] == "Mono8 (8 bit, mono)"
    for colour in ("red", "green", "blue"):
        capture = next(s["result"] for s in done if s["step"] == f"capture/bars/{colour}")
        assert capture["frames"] == ["frame-000.dng"] and capture["darks"] == []
        decoded = decode_raw(folder / capture["folder"] / "frame-000.dng")  # exactly the delivered ramp
        frame_id = capture["camera"][0]["frame_id"]
        ramp = mono8_ramp(frame_id, 192, 256).astype(np.float32) / np.float32(255)
        assert decoded.layout == "mono" and np.array_equal(decoded.mosaic, ramp)
        probe = next(s["result"] for s in done if s["step"] == f"probe/bars/{colour}")["auto_exposure"]
        assert 0.5 < probe["probe_peak"] <= 1.0  # the ramp, read on the ROI through the registration
    bars = metrics["targets"][0]
    assert set(bars["colours"]) == {"red", "green", "blue"}
    for colour in bars["colours"].values():
        assert 0.5 < colour["peak"] <= 1.0 and colour["capture"]["psnr_amplitude_db"] > 0
    (capture_png,) = folder.rglob("capture.png")
    assert read_image(capture_png).shape == (48, 80, 3)
