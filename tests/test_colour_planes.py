"""Registered colour planes and the merged, scored capture: exact gains and scores on analytic planes, the CFA
positions' coordinates, the warnings, and a DPAC colour chart captured on the simulated bench scoring like
benchctl's own simulated reconstruction."""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial

import msgspec
import numpy as np
import pytest
import torch
from conftest import SMALL_BENCH, mono_exposure, sim_exposure

from benchctl.calibration.calibrated import Calibrated
from benchctl.capture.colour_planes import (
    LOW_SIGNAL,
    merge_capture,
    registered_plane,
    registered_saturation,
    roi_saturation,
)
from benchctl.capture.raw import RawImage, subtract_dark
from benchctl.capture.registration import apply_homography
from benchctl.devices.sim import physics
from benchctl.errors import BenchctlError
from benchctl.holograms.scene import compute_scene
from benchctl.optics import colour_scores, crop_roi
from benchctl.profiles import Profile
from benchctl.targets import load_target, prepare_target

RGGB = np.array([[0, 1], [1, 2]], dtype=np.uint8)


def raw_image(mosaic: np.ndarray, cfa: np.ndarray = RGGB, saturated: np.ndarray | None = None) -> RawImage:
    mosaic = mosaic.astype(np.float32)
    return RawImage(mosaic, cfa, np.zeros(mosaic.shape, bool) if saturated is None else saturated,
                    np.zeros((2, 2)), 1.0, "synthetic")


def roi_pixels_in_mosaic(homography: np.ndarray, shape: tuple[int, int], roi: tuple[int, int]) -> np.ndarray:
    """(h, w, 2) mosaic coordinates (x, y) of every ROI pixel's centre."""
    top, left = (shape[0] - roi[0]) // 2, (shape[1] - roi[1]) // 2
    rows, cols = np.indices(roi)
    mapped = apply_homography(homography, np.column_stack([cols.ravel() + left, rows.ravel() + top]))
    return mapped.reshape(*roi, 2)


# -- registered planes ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("cfa", [RGGB, np.array([[1, 2], [0, 1]], dtype=np.uint8)])
def test_each_colour_is_read_at_its_own_pixels_positions(cfa: np.ndarray) -> None:
    """Every CFA position holds a linear function of its own mosaic coordinates, one function per colour:
    registered, each colour equals its function at the homography's image of every ROI pixel, within OpenCV
    4.x's 1/32-pixel interpolation positions (1.5e-4 here; 5.x is exact). Half a mosaic pixel's slip of any
    position's plane homography would be off by 5e-4 or more."""
    ys, xs = np.indices((120, 160)).astype(np.float64)
    functions = [lambda x, y: 0.2 + 0.002 * x + 0.001 * y,
                 lambda x, y: 0.5 - 0.0015 * x + 0.003 * y,
                 lambda x, y: 0.1 + 0.0025 * x - 0.002 * y]
    colour_at = cfa[ys.astype(int) % 2, xs.astype(int) % 2]
    mosaic = np.choose(colour_at, [f(xs, ys) for f in functions])
    homography = np.array([[1.9, -0.1, 12.0], [0.1, 1.9, 8.0], [0.0, 0.0, 1.0]])
    where = roi_pixels_in_mosaic(homography, (48, 64), (40, 56))
    for colour, function in enumerate(functions):
        plane = registered_plane(raw_image(mosaic, cfa), colour, homography, (48, 64), (40, 56))
        assert plane.shape == (40, 56) and plane.dtype == np.float32
        assert plane == pytest.approx(function(where[..., 0], where[..., 1]), abs=2e-4)


def test_saturation_is_traced_to_the_roi_pixels_it_touches() -> None:
    mosaic = np.full((120, 160), 0.5)
    saturated = np.zeros(mosaic.shape, bool)
    saturated[40:60, 60:80] = True  # a clipped patch, all four CFA positions
    image = raw_image(mosaic, saturated=saturated)
    # ROI pixel (r, c) is target pixel (c + 4, r + 4), mosaic (2 c + 18, 2 r + 18), red-plane pixel (c + 9, r + 9);
    # the red plane's clipped pixels are its rows 20..29 and columns 30..39
    homography = np.array([[2.0, 0, 10.0], [0, 2.0, 10.0], [0, 0, 1]])
    mask = registered_saturation(image, 0, homography, (48, 64), (40, 56))
    rows, cols = np.nonzero(mask)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (11, 20, 21, 30)
    assert mask.sum() == 100
    assert roi_saturation(image, 0, homography, (48, 64), (40, 56)) == pytest.approx(mask.mean())
    assert roi_saturation(raw_image(mosaic), 1, homography, (48, 64), (40, 56)) == 0.0


# -- merging and scoring -------------------------------------------------------------------------------------------


def test_planes_that_match_the_target_score_perfectly_with_their_gains() -> None:
    target = torch.rand((3, 30, 40), generator=torch.Generator().manual_seed(0))
    gains = (2.0, 3.0, 0.5)
    planes = {c: ((target[c] / gains[c]) ** 2).numpy() for c in range(3)}
    merged = merge_capture(planes, target)
    assert merged.merged.gains == pytest.approx({0: 2.0, 1: 3.0, 2: 0.5}, rel=1e-5)
    for c in range(3):
        assert merged.scores[c]["psnr_amplitude_db"] > 90 and merged.scores[c]["ssim_amplitude"] == pytest.approx(1.0)
    assert torch.allclose(merged.merged.amplitude, target, atol=1e-5)
    assert torch.allclose(merged.merged.linear, target.square(), atol=1e-5)
    assert merged.merged_scores["psnr_linear_db"] > 90 and merged.warnings == []


def test_scores_of_a_flat_capture_follow_from_the_targets_statistics() -> None:
    """Red captured flat (signal 0.25) against a 0.2 / 0.8 checkerboard: the least-squares gain makes the
    amplitude the target's mean 0.5, so the amplitude MSE is the target's variance 0.09 and the linear MSE is
    ((0.25 - 0.04)^2 + (0.25 - 0.64)^2) / 2 = 0.0981. Green and blue are black in the target and not captured."""
    target = torch.zeros((3, 20, 20))
    target[0] = torch.where((torch.arange(20)[:, None] + torch.arange(20)[None, :]) % 2 == 0, 0.2, 0.8)
    merged = merge_capture({0: np.full((20, 20), 0.25, np.float32)}, target)
    assert merged.merged.gains == {0: pytest.approx(1.0)}
    assert merged.scores[0]["psnr_amplitude_db"] == pytest.approx(10 * math.log10(1 / 0.09), abs=1e-4)
    assert merged.scores[0]["psnr_linear_db"] == pytest.approx(10 * math.log10(1 / 0.0981), abs=1e-4)
    assert torch.equal(merged.merged.linear[1:], torch.zeros((2, 20, 20)))
    # all three planes at once: green and blue are exact (black on black), red's MSE is a third
    assert merged.merged_scores["psnr_linear_db"] == pytest.approx(10 * math.log10(3 / 0.0981), abs=1e-4)
    assert merged.warnings == []


def test_warnings_name_saturation_low_signal_and_missing_colours() -> None:
    target = torch.full((3, 10, 10), 0.5)
    planes = {0: np.full((10, 10), 0.5, np.float32), 1: np.full((10, 10), 0.01, np.float32)}
    merged = merge_capture(planes, target, saturation={0: 0.0123})
    assert merged.warnings == [
        "red: 1.23% of the ROI is saturated; that colour reads low there",
        f"green: low signal, peak 1.0% of full scale (below {LOW_SIGNAL:.0%}): expose longer or raise the laser power",
        "not captured: blue (present in the target; scored as black)",
    ]
    assert merged.merged.linear[2].abs().max() == 0


def test_merge_refuses_planes_that_do_not_fit_the_target() -> None:
    target = torch.zeros((3, 10, 12))
    with pytest.raises(BenchctlError, match=r"green plane is \(10, 10\), the target ROI is \(10, 12\)"):
        merge_capture({1: np.zeros((10, 10))}, target)
    with pytest.raises(BenchctlError, match=r"colour plane 3 is not 0 \(red\), 1 \(green\) or 2 \(blue\)"):
        merge_capture({3: np.zeros((10, 12))}, target)
    with pytest.raises(BenchctlError, match=r"target ROI must be \(3, h, w\) amplitude, got shape \(10, 12\)"):
        merge_capture({}, torch.zeros((10, 12)))


# -- the simulated bench -------------------------------------------------------------------------------------------

# The conftest's SMALL_BENCH: a 64 x 96 SLM (ROI 48 x 80, 8 um, 20 mm) behind the 0.5 x Nyquist iris, imaged at
# 2.175 sensor pixels per SLM pixel (the default bench's sampling: 1.09 CFA-plane pixels per SLM pixel), turned 3
# degrees.
LINEAR_MARGIN_DB = 0.5
"""|capture - simulation| of the merged linear PSNR (measured 0.07 dB)."""
SRGB_MARGIN_DB = 1.5
"""|capture - simulation| of the merged sRGB PSNR (measured 0.75 dB: sRGB magnifies the dark bars' noise)."""
AMPLITUDE_MARGIN_DB = 1.0
"""|capture - simulation| of each colour's amplitude PSNR (measured 0.57 / 0.21 / 0.74 dB for R / G / B: the
camera resamples the image twice, sensor and registration, which blurs the bars' edges)."""


@pytest.fixture
def profile(make_bench_profile: Callable[..., Profile]) -> Profile:
    return make_bench_profile(SMALL_BENCH, setpoints_mw={"red": 20, "green": 6, "blue": 6},
                              sim={"seed": 11, "imaging": {"magnification": 1.0875, "rotation_deg": 3.0}})


@pytest.mark.parametrize("sensor", ["bayer", "mono"])
def test_a_captured_colour_chart_scores_like_the_simulated_reconstruction(profile: Profile, sensor: str) -> None:
    """DPAC holograms of the colour bars, one colour at a time, each rendered by a bench whose true response
    equals the profile's linear table at that wavelength (so the prediction is the truth), dark-subtracted,
    registered with the true homography, merged: the scores match benchctl's simulated reconstruction. The same
    with a monochrome sensor (every colour read from every pixel): within the same margins (measured: mono and
    Bayer within 0.01 dB of each other, docs/genicam.md)."""
    shape, roi = profile.slm.shape, profile.optics.roi
    target = prepare_target(load_target("chart:bars", roi), shape, roi)
    scene = compute_scene(target, Calibrated(profile), "dpac")
    homography = physics.camera_homography(profile)
    planes, saturation = {}, {}
    for colour, channel in enumerate(profile.channels):
        linear = msgspec.structs.replace(profile.sim.slm, two_pi_nm=channel.wavelength_nm, gamma=1.0, zero_order=0.0)
        calibrated = msgspec.structs.replace(profile, sim=msgspec.structs.replace(profile.sim, slm=linear))
        powers_w = {channel.name: channel.setpoint_mw * 1e-3}
        exposure = sim_exposure if sensor == "bayer" else partial(mono_exposure, colour=colour)
        lit = exposure(calibrated, scene.colours[colour].gray, powers_w, 2 * colour + 1)
        dark = exposure(calibrated, None, {}, 2 * colour + 2)
        image = subtract_dark(lit, dark)
        assert image.monochrome == (sensor == "mono")
        planes[colour] = registered_plane(image, colour, homography, shape, roi)
        saturation[colour] = roi_saturation(image, colour, homography, shape, roi)
        assert 0.3 < np.percentile(planes[colour], 99.9) < 0.8  # well exposed
    merged = merge_capture(planes, crop_roi(target, roi), saturation)
    assert merged.warnings == []
    assert merged.merged.linear.shape == (3, 48, 80)
    for colour in range(3):
        captured, simulated = merged.scores[colour], scene.colours[colour].scores
        assert abs(captured["psnr_amplitude_db"] - simulated["psnr_amplitude_db"]) < AMPLITUDE_MARGIN_DB
    assert abs(merged.merged_scores["psnr_linear_db"] - scene.merged_scores["psnr_linear_db"]) < LINEAR_MARGIN_DB
    assert abs(merged.merged_scores["psnr_srgb_db"] - scene.merged_scores["psnr_srgb_db"]) < SRGB_MARGIN_DB
    # the same planes mirrored (what a registration missing the SLM's flip would give) fall far outside the margins
    mirrored = merge_capture({c: plane[:, ::-1].copy() for c, plane in planes.items()}, crop_roi(target, roi))
    assert mirrored.merged_scores["psnr_linear_db"] < scene.merged_scores["psnr_linear_db"] - 3 * LINEAR_MARGIN_DB


def test_a_scene_of_some_colours_is_scored_on_their_planes(profile: Profile) -> None:
    """`--colours green` computes one plane: its merged (sRGB) scores compare it with the target's green plane
    alone, not with a colour image whose red and blue it never tried to show (measured on the paper geometry
    before: 8.4 dB for every method)."""
    shape, roi = profile.slm.shape, profile.optics.roi
    target = prepare_target(load_target("chart:bars", roi), shape, roi)
    green = compute_scene(target, Calibrated(profile), "dpac", colours=["green"])
    only_green = crop_roi(target, roi) * torch.tensor([0.0, 1.0, 0.0]).view(3, 1, 1)
    assert green.merged_scores == colour_scores(green.merged_linear, only_green)
    assert green.merged_scores["psnr_srgb_db"] > colour_scores(green.merged_linear, crop_roi(target, roi))[
        "psnr_srgb_db"] + 3
    full = compute_scene(target, Calibrated(profile), "dpac")
    assert full.merged_scores == colour_scores(full.merged_linear, crop_roi(target, roi))
