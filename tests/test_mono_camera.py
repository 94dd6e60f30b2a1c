"""A monochrome camera through the capture pipeline: each colour is exposed alone, so its light is read from every
pixel of the mono frame. On the simulated bench (registration, colour planes, merge and scores) with a monochrome
sensor made from the simulator's own renders, and end to end through `benchctl run` with Aravis's fake camera in
Mono8 / Mono16 (tests/test_display_slm.py runs the same with the SLM on a real X server)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
from conftest import SMALL_BENCH, SMALL_PROFILE
from gigevision import mono8_ramp
from test_colour_planes import AMPLITUDE_MARGIN_DB, LINEAR_MARGIN_DB, SRGB_MARGIN_DB
from test_registration import CORNER_TOLERANCE, GEOMETRY, POWERS_W, corner_error

from benchctl.capture.colour_planes import merge_capture, registered_plane, roi_saturation
from benchctl.capture.raw import RawImage, decode_raw, subtract_dark
from benchctl.capture.registration import Registration, dot_grid_target, dots_in_capture, fit_registration
from benchctl.cgh import OpticalSetup, get_method
from benchctl.devices.sim import bench
from benchctl.devices.slm import slm_for
from benchctl.cli import main
from benchctl.dng import CFA_LAYOUTS, dng_bytes
from benchctl.images import read_image
from benchctl.optics import crop_roi
from benchctl.profiles import Profile, load_profile
from benchctl.runner.calibration import Calibration
from benchctl.runner.holograms import compute_scene
from benchctl.targets import load_target, prepare_target


def mono_exposure(profile: Profile, gray: np.ndarray | None, powers_w: dict[str, float], colour: int,
                  frame: int) -> RawImage:
    """What a monochrome sensor records of `gray` lit by one colour (plane index `colour`; no light: dark), as a
    monochrome DNG decoded. Made from the simulator's renders with each of the four Bayer layouts: every pixel is
    taken from a render in which its site carries that colour's filter, so the sensor responds to the colour alike
    at every pixel (the filter's response; a flat mono response differs by a gain that the merge's balance takes)."""
    sensor = profile.sim.sensor
    mono = np.zeros(sensor.shape, dtype=np.uint16)
    filled = np.zeros(sensor.shape, dtype=bool)
    site = np.indices(sensor.shape) % 2  # the margins are even: the full sensor's sites are the active area's
    for layout, cells in CFA_LAYOUTS.items():
        with_layout = msgspec.structs.replace(profile, sim=msgspec.structs.replace(
            profile.sim, sensor=msgspec.structs.replace(sensor, cfa=layout)))
        mosaic = bench.render_mosaic(with_layout, gray, powers_w, exposure_s=0.01, iso=100, frame=frame)
        take = (np.reshape(cells, (2, 2))[site[0], site[1]] == colour) & ~filled
        mono[take], filled[take] = mosaic[take], True
    assert filled.all()
    return decode_raw(dng_bytes(mono, cfa=None, black_level=sensor.black_level, white_level=sensor.white_level,
                                active_area=sensor.active_area))


@pytest.fixture
def chart_profile(make_bench_profile: Callable[..., Profile]) -> Profile:
    """test_colour_planes's bench: 64 x 96 SLM, 2.175 sensor pixels per SLM pixel, turned 3 degrees."""
    return make_bench_profile(SMALL_BENCH, setpoints_mw={"red": 20, "green": 6, "blue": 6},
                              sim={"seed": 11, "imaging": {"magnification": 1.0875, "rotation_deg": 3.0}})


def test_a_colour_chart_captured_in_mono_scores_like_the_simulated_reconstruction(chart_profile: Profile) -> None:
    """test_colour_planes's chart test with a monochrome sensor: DPAC holograms of the colour bars, each colour
    alone, dark-subtracted, every colour's plane read from the whole mono mosaic with the true registration,
    merged and scored: within the same margins of benchctl's simulated reconstruction."""
    profile = chart_profile
    shape, roi = profile.slm.shape, profile.optics.roi
    target = prepare_target(load_target("chart:bars", roi), shape, roi)
    scene = compute_scene(target, profile, "dpac")
    homography = bench.camera_homography(profile)
    planes, saturation = {}, {}
    for colour, channel in enumerate(profile.channels):
        linear = msgspec.structs.replace(profile.sim.slm, two_pi_nm=channel.wavelength_nm, gamma=1.0, zero_order=0.0)
        calibrated = msgspec.structs.replace(profile, sim=msgspec.structs.replace(profile.sim, slm=linear))
        lit = mono_exposure(calibrated, scene.colours[colour].gray, {channel.name: channel.setpoint_mw * 1e-3},
                            colour, 2 * colour + 1)
        image = subtract_dark(lit, mono_exposure(calibrated, None, {}, colour, 2 * colour + 2))
        assert image.layout == "mono"
        planes[colour] = registered_plane(image, colour, homography, shape, roi)
        saturation[colour] = roi_saturation(image, colour, homography, shape, roi)
        assert 0.3 < np.percentile(planes[colour], 99.9) < 0.8  # well exposed
    merged = merge_capture(planes, crop_roi(target, roi), saturation)
    assert merged.warnings == []
    for colour in range(3):
        captured, simulated = merged.scores[colour], scene.colours[colour].scores
        assert abs(captured["psnr_amplitude_db"] - simulated["psnr_amplitude_db"]) < AMPLITUDE_MARGIN_DB
    assert abs(merged.merged_scores["psnr_linear_db"] - scene.merged_scores["psnr_linear_db"]) < LINEAR_MARGIN_DB
    assert abs(merged.merged_scores["psnr_srgb_db"] - scene.merged_scores["psnr_srgb_db"]) < SRGB_MARGIN_DB


@pytest.mark.parametrize("channel, colour", [("red", 0), ("blue", 2)])
def test_registration_finds_the_dots_in_a_mono_capture(make_bench_profile: Callable[..., Profile], channel: str,
                                                       colour: int) -> None:
    """test_registration's dot grid, captured by a monochrome sensor: the homography is recovered as closely as
    from a Bayer capture (its tolerance)."""
    profile = make_bench_profile(GEOMETRY)
    amplitude, points = dot_grid_target(profile.slm.shape, profile.optics.roi, (12, 21))
    gray = slm_for(profile).encode(get_method("dpac")(amplitude, OpticalSetup.from_profile(profile, channel)),
                                   channel)
    image = mono_exposure(profile, gray, {channel: POWERS_W[channel]}, colour, 1)
    assert image.saturation_fraction == 0
    fit = fit_registration(points, dots_in_capture(image, colour))
    assert fit.inliers >= 0.98 * fit.points and fit.scale == pytest.approx(2.0, rel=0.005)
    assert corner_error(profile, fit.homography, bench.camera_homography(profile)) < CORNER_TOLERANCE * 2.0


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
    profile.write_text(SMALL_PROFILE.replace("bit_depth = 8", "bit_depth = 8\nsettle_ms = 0") + """
[camera]
driver = "genicam"
serial = "1"
pixel_format = "Mono8"
region = [0, 0, 256, 192]
exposure_s = 0.01
gain = 0.0
""")
    store_registration(profile, 2.0, (32.5, 32.5))
    procedure = tmp_path / "capture.toml"
    procedure.write_text(CAPTURE_ON_A_FAKE_CAMERA)
    assert main(["run", str(procedure), "--profile", str(profile), "--out", str(tmp_path / "runs")]) == 0
    folder, metrics, done = finished_run(tmp_path / "runs")
    assert json.loads((folder / "devices.json").read_text())["camera"]["pixel_format"] == "Mono8 (8 bit, mono)"
    for colour in ("red", "green", "blue"):
        assert [p.name for p in (folder / "raw" / "bars" / colour).glob("*.dng")] == ["frame-000.dng"]
        frame_id = next(s["result"] for s in done if s["step"] == f"capture/bars/{colour}")["camera"][0]["frame_id"]
        decoded = decode_raw(folder / "raw" / "bars" / colour / "frame-000.dng")  # exactly the delivered ramp
        ramp = mono8_ramp(frame_id, 192, 256).astype(np.float32) / np.float32(255)
        assert decoded.layout == "mono" and np.array_equal(decoded.mosaic, ramp)
        probe = next(s["result"] for s in done if s["step"] == f"probe/bars/{colour}")["auto_exposure"]
        assert 0.5 < probe["probe_peak"] <= 1.0  # the ramp, read on the ROI through the registration
    bars = metrics["targets"][0]
    assert set(bars["colours"]) == {"red", "green", "blue"}
    for colour in bars["colours"].values():
        assert 0.5 < colour["peak"] <= 1.0 and colour["capture"]["psnr_amplitude_db"] > 0
    assert read_image(folder / "images" / "bars" / "capture.png").shape == (48, 80, 3)
