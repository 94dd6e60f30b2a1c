"""Camera-SLM registration: the dot-grid pattern, dot detection under every symmetry of the grid, the RANSAC fit
and its refusals, the coordinate helpers, and the whole chain on the simulated bench against the simulator's
true homography (`physics.camera_homography`)."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import sim_exposure

from benchctl.calibration.setups import optical_setup
from benchctl.capture.raw import RawImage
from benchctl.capture.registration import (
    MAX_RMS_TARGET_PX,
    Registration,
    RegistrationError,
    apply_homography,
    dot_grid_target,
    dots_in_capture,
    find_dots,
    fit_registration,
    plane_homography,
    warp_to_roi,
)
from benchctl.cgh import get_method
from benchctl.devices.sim import physics
from benchctl.devices.slm import save_lut, slm_for
from benchctl.errors import BenchctlError
from benchctl.optics.aberration import pupil_radius_m
from benchctl.optics.fitted import FittedOptics
from benchctl.optics.metrics import centred_slices
from benchctl.profiles import Profile

# BENCH_PROFILE's 128 x 192 SLM with the ROI widened to 96 x 168 (the default 12 x 21 grid at 8 px spacing), imaged
# at 8 um / 4 um x 1.0 = 2 sensor pixels per SLM pixel, turned 3 degrees, onto its 300 x 440 sensor. The [sim.slm]
# response is the default (uncalibrated: the profile's linear tables are off by 0.88 / 1.15 / 1.33 x 2 pi and gamma
# 1.05), as at the first registration of a bench.
GEOMETRY = {"optics": {"roi": [96, 168]},
            "sim": {"seed": 3, "beam": {"efficiency": 1e-5}, "sensor": {"margin": [4, 10]},
                    "imaging": {"rotation_deg": 3.0, "offset_px": [6.0, -15.0]}}}
POWERS_W = {"red": 40e-3, "green": 2e-3, "blue": 2e-3}  # peaks at 30-80 % of full scale, nothing clipped
CORNER_TOLERANCE = 0.4
"""Largest distance, in target-plane pixels, between where the fit and the simulator put the ROI's corners with
an uncalibrated SLM (measured on these grids: 0.29 / 0.19 / 0.10 for red / green / blue, 0.07-0.19 for the
mirrored, turned and magnified cases; calibrated, see the test below: 0.03-0.06)."""


@pytest.fixture
def profile(make_bench_profile: Callable[..., Profile]) -> Profile:
    return make_bench_profile(GEOMETRY)


def dot_grid_capture(profile: Profile, channel: str, method: str = "dpac", grid: tuple[int, int] = (12, 21),
                     power_w: float | None = None, exposure: Callable[..., RawImage] = sim_exposure,
                     ) -> tuple[RawImage, np.ndarray]:
    """The dot-grid hologram for `channel`, encoded by the profile's SLM (its tables and flips), captured (by
    `exposure`, conftest's sim_exposure or mono_exposure)."""
    amplitude, points = dot_grid_target(profile.slm.shape, profile.optics.roi, grid)
    phase = get_method(method)(amplitude, optical_setup(profile, channel))
    gray = slm_for(profile).encode(phase, channel)
    return exposure(profile, gray, {channel: POWERS_W[channel] if power_w is None else power_w}), points


def roi_corners(profile: Profile) -> np.ndarray:
    """The outer corners of the ROI's corner pixels, as (x, y) target-plane coordinates."""
    rows, cols = centred_slices(profile.slm.shape, profile.optics.roi)
    return np.array([[cols.start - 0.5, rows.start - 0.5], [cols.stop - 0.5, rows.start - 0.5],
                     [cols.start - 0.5, rows.stop - 0.5], [cols.stop - 0.5, rows.stop - 0.5]])


def corner_error(profile: Profile, homography: np.ndarray, truth: np.ndarray) -> float:
    """Largest distance (sensor pixels) between the two homographies' images of the ROI's corners."""
    corners = roi_corners(profile)
    return float(np.hypot(*(apply_homography(homography, corners) - apply_homography(truth, corners)).T).max())


# -- the pattern ---------------------------------------------------------------------------------------------------


def test_dot_grid_lists_every_dot_but_the_marker_row_by_row() -> None:
    amplitude, points = dot_grid_target((128, 192), (96, 168))
    assert amplitude.dtype == torch.float32 and amplitude.shape == (128, 192)
    assert points.shape == (12 * 21 - 1, 2) and points.dtype == np.float64
    # ROI rows 16..111, cols 12..179: 8 px cells, cell (row 0, col 0) centred on (x, y) = (15.5, 19.5)
    assert points[0] == pytest.approx([23.5, 19.5])  # (row 0, col 1): the marker (row 0, col 0) is left out
    assert points[19] == pytest.approx([175.5, 19.5])  # the end of the first row
    assert points[20] == pytest.approx([15.5, 27.5])  # (row 1, col 0)
    assert points[-1] == pytest.approx([175.5, 107.5])
    image = amplitude.numpy()
    rows, cols = centred_slices((128, 192), (96, 168))
    outside = np.ones(image.shape, bool)
    outside[rows, cols] = False
    assert not image[outside].any()
    assert not image[16:24, 12:20].any()  # the marker's cell is dark
    assert image.max() == 1.0


@pytest.mark.parametrize("roi, tolerance", [((90, 144), 1e-9), ((90, 140), 0.03)])
def test_each_dot_is_centred_on_its_point(roi: tuple[int, int], tolerance: float) -> None:
    """Per cell, the amplitude's centroid is the listed point: exactly where the spacing puts dot centres on
    pixel centres or between two (15 x 16 px cells), within 0.03 px of sampling asymmetry otherwise."""
    amplitude, points = dot_grid_target((100, 150), roi, grid=(6, 9), radius_px=3.2)
    image = amplitude.numpy().astype(np.float64)
    ys, xs = np.indices(image.shape)
    for x, y in points:
        cell = (abs(xs - x) < 7) & (abs(ys - y) < 7)
        weight = np.where(cell, image, 0.0)
        assert (weight * xs).sum() / weight.sum() == pytest.approx(x, abs=tolerance)
        assert (weight * ys).sum() / weight.sum() == pytest.approx(y, abs=tolerance)
        assert weight.sum() == pytest.approx(math.pi * 3.2**2, rel=0.05)


def test_dot_grid_refuses_dots_that_do_not_fit() -> None:
    with pytest.raises(BenchctlError, match=r"dot radius 4 px does not fit a 12 x 21 grid .* 0.5 .. 3 px"):
        dot_grid_target((128, 192), (96, 168), radius_px=4.0)
    with pytest.raises(BenchctlError, match=r"at least 3 x 3 dots, got 2 x 21"):
        dot_grid_target((128, 192), (96, 168), grid=(2, 21))


# -- finding the dots in images made with a known homography -----------------------------------------------------


FLIP_X = np.array([[-1.0, 0, 191], [0, 1, 0], [0, 0, 1]])  # column x -> 191 - x on a 192-wide grid
FLIP_Y = np.array([[1.0, 0, 0], [0, -1, 127], [0, 0, 1]])


def turned(degrees: float, scale: float, centre: tuple[float, float] = (200.0, 150.0)) -> np.ndarray:
    """Similarity: the grid's centre (95.5, 63.5) to `centre`, scaled and turned clockwise as displayed."""
    a = math.radians(degrees)
    linear = scale * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    homography = np.eye(3)
    homography[:2, :2] = linear
    homography[:2, 2] = np.array(centre) - linear @ [95.5, 63.5]
    return homography


@pytest.mark.parametrize("name, homography", [
    ("plain", turned(0.0, 1.5)),
    ("turned, magnified", turned(-4.0, 2.2)),
    ("mirrored in x", turned(2.0, 1.5) @ FLIP_X),
    ("turned by 180 degrees", turned(180.0, 1.3)),
    ("mirrored in y", turned(0.0, 1.5) @ FLIP_Y),
    ("a quarter turn", turned(92.0, 1.5, centre=(150.0, 200.0))),
    ("perspective", np.array([[1.5, 0.02, 40.0], [-0.01, 1.45, 30.0], [2e-4, -1e-4, 1.0]])),
])
def test_find_dots_orders_the_points_under_any_symmetry(name: str, homography: np.ndarray) -> None:
    """An ideal image of the pattern warped by a known homography: every dot found, in the target's order."""
    amplitude, points = dot_grid_target((128, 192), (96, 168))
    image = cv2.warpPerspective(amplitude.numpy() ** 2, homography, (400, 400), flags=cv2.INTER_LINEAR)
    found = find_dots(image)
    assert found.shape == points.shape and np.isfinite(found).all()
    errors = np.hypot(*(found - apply_homography(homography, points)).T)
    assert errors.max() < 0.1, name


def test_find_dots_says_how_many_it_found_when_the_grid_is_not_all_in_view() -> None:
    amplitude, _ = dot_grid_target((128, 192), (96, 168))
    image = cv2.warpPerspective(amplitude.numpy(), turned(0.0, 2.0), (400, 300))
    image[:, 200:] = 0  # the right half of the grid is cut off
    with pytest.raises(RegistrationError, match=r"found 1[0-9]{2} of the 251 dots of a 12 x 21 dot grid"):
        find_dots(image)


def test_a_grid_of_another_size_is_not_taken_for_the_expected_one() -> None:
    amplitude, _ = dot_grid_target((128, 192), (96, 168), grid=(6, 10))
    with pytest.raises(RegistrationError, match=r"found 59 of the 251 dots of a 12 x 21 dot grid"):
        find_dots(cv2.warpPerspective(amplitude.numpy(), turned(1.0, 2.0), (400, 300)))
    assert np.isfinite(find_dots(cv2.warpPerspective(amplitude.numpy(), turned(1.0, 2.0), (400, 300)),
                                 grid=(6, 10))).all()


def test_a_grid_without_its_marker_is_refused() -> None:
    """All four corners present: which corner is which cannot be told, so nothing is guessed."""
    amplitude, _ = dot_grid_target((128, 192), (96, 168))
    image = amplitude.numpy().copy()
    image[16:24, 12:20] = image[16:24, 20:28]  # copy the neighbouring dot into the marker's cell
    with pytest.raises(RegistrationError,
                       match=r"no 12 x 21 part of the 252 spots on the lattice shows the marker \(exactly one empty "
                             r"corner\): the fullest holds 252 spots \(the grid has 251\) with 0 corners empty"):
        find_dots(cv2.warpPerspective(image, turned(0.0, 1.5), (400, 300)))


# -- the fit -------------------------------------------------------------------------------------------------------


def test_fit_recovers_a_homography_exactly_and_leaves_out_dots_not_found() -> None:
    _, points = dot_grid_target((128, 192), (96, 168))
    truth = turned(3.0, 2.0) @ FLIP_X
    image_points = apply_homography(truth, points)
    image_points[[5, 77, 200]] = np.nan  # three dots not found
    fit = fit_registration(points, image_points)
    assert fit.points == 248 and fit.inliers == 248
    assert fit.rms_px < 1e-5 and fit.max_px < 1e-5
    assert fit.homography == pytest.approx(truth / truth[2, 2], abs=1e-5)  # OpenCV refines to ~1e-6 px
    assert fit.scale == pytest.approx(2.0) and fit.mirrored


def test_ransac_ignores_a_few_wrong_dots() -> None:
    _, points = dot_grid_target((128, 192), (96, 168))
    truth = turned(-2.0, 1.7)
    rng = np.random.default_rng(1)
    image_points = apply_homography(truth, points) + rng.normal(0, 0.2, points.shape)
    image_points[::25] += rng.uniform(10, 30, image_points[::25].shape)  # 11 dots badly misplaced
    fit = fit_registration(points, image_points)
    assert fit.inliers == 240 and fit.points == 251
    assert fit.rms_px == pytest.approx(0.2 * math.sqrt(2), rel=0.15)
    assert corner_error_between(fit.homography, truth) < 0.3


def corner_error_between(homography: np.ndarray, truth: np.ndarray) -> float:
    corners = np.array([[11.5, 15.5], [179.5, 15.5], [11.5, 111.5], [179.5, 111.5]])
    return float(np.hypot(*(apply_homography(homography, corners) - apply_homography(truth, corners)).T).max())


def test_a_fit_with_too_few_inliers_is_refused() -> None:
    _, points = dot_grid_target((128, 192), (96, 168))
    image_points = apply_homography(turned(0.0, 2.0), points)
    rng = np.random.default_rng(2)
    image_points[::3] = rng.uniform(0, 400, image_points[::3].shape)  # a third of the matches are wrong
    with pytest.raises(RegistrationError, match=r"registration refused: only 167 of 251 points within [\d.]+ px.*"
                                                r"needs 80% inliers"):
        fit_registration(points, image_points)


def test_a_fit_scattered_beyond_the_rms_limit_is_refused() -> None:
    _, points = dot_grid_target((128, 192), (96, 168))
    rng = np.random.default_rng(3)
    image_points = apply_homography(turned(0.0, 2.0), points) + rng.normal(0, 0.6, points.shape)
    with pytest.raises(RegistrationError, match=r"the RMS is 0\.[4-6]\d* target-plane pixels, above the 0\.3 px"):
        fit_registration(points, image_points, max_rms_target_px=0.3, ransac_target_px=3.0)
    assert fit_registration(points, image_points, ransac_target_px=3.0).rms_target_px < MAX_RMS_TARGET_PX


def test_implausible_or_degenerate_homographies_are_refused() -> None:
    _, points = dot_grid_target((128, 192), (96, 168))
    stretched = np.array([[3.0, 0, 10], [0, 1.0, 10], [0, 0, 1]])
    with pytest.raises(RegistrationError, match=r"stretches one direction 3 x more than the other"):
        fit_registration(points, apply_homography(stretched, points))
    projective = np.array([[1.0, 0, 0], [0, 1.0, 0], [3e-3, 0, 1]])
    with pytest.raises(RegistrationError, match=r"perspective divisor ranges 1\.0[0-9]* \.\. 1\.5"):
        fit_registration(points, apply_homography(projective, points))
    collapsed = points.copy()
    collapsed[:, 1] = 50.0  # every point on one line
    with pytest.raises(RegistrationError, match=r"no homography fits the 251 point pairs|degenerate"):
        fit_registration(points, collapsed)
    with pytest.raises(RegistrationError, match=r"at least 8 point pairs, got 5"):
        fit_registration(points[:5], points[:5])


def test_registration_round_trips_through_json() -> None:
    _, points = dot_grid_target((128, 192), (96, 168))
    fit = fit_registration(points, apply_homography(turned(1.0, 2.0), points))
    again = Registration.from_dict(json.loads(json.dumps(fit.to_dict())))
    assert np.array_equal(again.homography, fit.homography)
    assert (again.rms_px, again.max_px, again.inliers, again.points) == (fit.rms_px, fit.max_px, 251, 251)
    damaged = fit.to_dict()
    del damaged["inliers"]
    with pytest.raises(RegistrationError, match=r"lacks the key 'inliers'"):
        Registration.from_dict(damaged)
    with pytest.raises(RegistrationError, match=r"'homography' must be 3 x 3"):
        Registration.from_dict({**fit.to_dict(), "homography": [[1, 0], [0, 1]]})


# -- coordinate helpers --------------------------------------------------------------------------------------------


# OpenCV 4.x interpolates at positions rounded to 1/32 pixel (5.x exactly): a linear image of slope a, b per
# pixel is then sampled within (|a| + |b|) / 64 of the exact value.
def test_warp_to_roi_samples_where_the_homography_maps_each_roi_pixel() -> None:
    """A linear image f(x, y) = 0.03 x - 0.02 y + 5 is interpolated exactly (to OpenCV's 1/32 px): the result is
    f at H(target pixel); one pixel's slip would be off by 0.02 or more."""
    ys, xs = np.indices((300, 400))
    image = (0.03 * xs - 0.02 * ys + 5.0).astype(np.float32)
    homography = turned(5.0, 1.6)
    out = warp_to_roi(image, homography, (128, 192), (96, 168))
    assert out.shape == (96, 168) and out.dtype == np.float32
    rows, cols = np.indices((96, 168))
    mapped = apply_homography(homography, np.column_stack([cols.ravel() + 12, rows.ravel() + 16]))
    expected = (0.03 * mapped[:, 0] - 0.02 * mapped[:, 1] + 5.0).reshape(96, 168)
    assert out == pytest.approx(expected, abs=0.05 / 64 + 1e-4)
    outside = warp_to_roi(image, turned(0.0, 1.0, centre=(900.0, 900.0)), (128, 192), (96, 168))
    assert not outside.any()  # zeros where the homography leaves the image


@pytest.mark.parametrize("offset", [(0, 0), (0, 1), (1, 0), (1, 1), (0.5, 0.5)])
def test_plane_homography_matches_the_cfa_layout(offset: tuple[float, float]) -> None:
    """Plane pixel (i, j) holds mosaic pixel (2 i + dy, 2 j + dx): warping the plane with the plane homography
    samples the same linear function as warping the mosaic with the mosaic homography (half a mosaic pixel's
    slip would be off by 0.0035 or more)."""
    ys, xs = np.indices((300, 400))

    def mosaic_value(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 0.007 * x + 0.013 * y

    dy, dx = offset
    plane = mosaic_value(2 * xs[:150, :200] + dx, 2 * ys[:150, :200] + dy).astype(np.float32)
    homography = turned(-3.0, 1.5)
    out = warp_to_roi(plane, plane_homography(homography, offset), (128, 192), (96, 168))
    rows, cols = np.indices((96, 168))
    mapped = apply_homography(homography, np.column_stack([cols.ravel() + 12, rows.ravel() + 16]))
    plane_slope = 2 * (0.007 + 0.013)  # per plane pixel
    assert out == pytest.approx(mosaic_value(mapped[:, 0], mapped[:, 1]).reshape(96, 168), abs=plane_slope / 64 + 1e-5)


# -- the simulated bench -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("channel, colour", [("red", 0), ("green", 1), ("blue", 2)])
def test_registration_recovers_the_simulators_homography(profile: Profile, channel: str, colour: int) -> None:
    image, points = dot_grid_capture(profile, channel)
    assert image.saturation_fraction == 0
    found = dots_in_capture(image, colour)
    assert np.isfinite(found).all()
    fit = fit_registration(points, found)
    truth = physics.camera_homography(profile)
    assert fit.inliers >= 0.98 * fit.points and not fit.mirrored
    assert fit.scale == pytest.approx(2.0, rel=0.005)
    assert corner_error(profile, fit.homography, truth) < CORNER_TOLERANCE * 2.0


@pytest.mark.parametrize("channel, colour", [("red", 0), ("green", 1), ("blue", 2)])
def test_a_calibrated_slm_registers_to_a_tenth_of_a_pixel(profile: Profile, make_bench_profile: Callable[..., Profile],
                                                          tmp_path: Path, channel: str, colour: int) -> None:
    """With the profile's lookup tables equal to the panel's true response the dots are imaged undistorted:
    corners within 0.1 target-plane pixel (measured 0.03 / 0.06 / 0.04 for red / green / blue)."""
    tables = {c.name: str(save_lut(tmp_path / f"{c.name}.csv", physics.true_lut(c.wavelength_m, 8, profile.sim.slm)))
              for c in profile.channels}
    calibrated = make_bench_profile(GEOMETRY, slm={"lut": tables})
    image, points = dot_grid_capture(calibrated, channel, power_w=POWERS_W[channel] / 2)
    assert image.saturation_fraction == 0
    fit = fit_registration(points, dots_in_capture(image, colour))
    assert fit.rms_target_px < 0.2
    assert corner_error(profile, fit.homography, physics.camera_homography(profile)) < 0.1 * 2.0


@pytest.mark.parametrize("method, magnification, rotation_deg, flips", [
    ("dpac", 1.4, 3.0, (True, False)),  # mirrored by the SLM's flip_x, turned, 2.8 sensor px per SLM px
    ("dpac", 0.6, -4.0, (True, True)),  # turned by 180 degrees by both flips, 1.2 sensor px per SLM px
    ("gs", 1.4, 2.0, (False, True)),  # Gerchberg-Saxton: light outside the ROI, speckled dots
])
def test_registration_recovers_mirrored_turned_and_magnified_geometry(
        make_bench_profile: Callable[..., Profile], method: str, magnification: float, rotation_deg: float,
        flips: tuple[bool, bool]) -> None:
    profile = make_bench_profile(GEOMETRY, slm={"flip_x": flips[0], "flip_y": flips[1]}, sim={
        "imaging": {"magnification": magnification, "rotation_deg": rotation_deg}, "sensor": {"shape": [400, 600]}})
    scale = magnification * 2.0
    truth = physics.camera_homography(profile)
    for flip, matrix in zip(flips, (FLIP_X, FLIP_Y)):
        truth = truth @ matrix if flip else truth  # the SLM displays the hologram mirrored
    image, points = dot_grid_capture(profile, "green", method)
    fit = fit_registration(points, dots_in_capture(image, 1))
    assert fit.mirrored == (flips[0] != flips[1])
    assert fit.scale == pytest.approx(scale, rel=0.01)
    assert corner_error(profile, fit.homography, truth) < CORNER_TOLERANCE * scale


def test_a_capture_without_light_is_refused_with_the_count(profile: Profile) -> None:
    dark = sim_exposure(profile, None, {})
    with pytest.raises(RegistrationError, match=r"found 0 of the 251 dots of a 12 x 21 dot grid: the image shows "
                                                r"no regular pattern"):
        dots_in_capture(dark, 1)


def test_a_grid_half_off_the_sensor_is_refused_with_the_count(make_bench_profile: Callable[..., Profile]) -> None:
    # the grid's right part misses the sensor
    profile = make_bench_profile(GEOMETRY, sim={"imaging": {"offset_px": [0.0, 190.0]}})
    image, _ = dot_grid_capture(profile, "green")
    with pytest.raises(RegistrationError, match=r"found 1[0-9]{2} of the 251 dots"):
        dots_in_capture(image, 1)


def test_an_aberrated_bench_registers_through_its_fitted_model(make_bench_profile: Callable[..., Profile]) -> None:
    """Defocus scales the image of a coherent grid and coma and a tilted beam move it: displayed through the ideal
    model the dots still form a clean grid (RMS 0.47 target pixel, under the limit) that puts the ROI's corners
    10.6 pixels from where the bench images them, a registration that would bake the aberrations into the mapping.
    Displayed through the bench's model (what model calibration fits; here the hidden values themselves) the dots
    land where they were meant to: corners 0.06 pixel off."""
    hidden = {"astigmatism_vertical": -0.3, "defocus": 0.6, "coma_vertical": 0.2, "coma_horizontal": -0.3}
    tilt_mrad = (0.4, -0.6)
    profile = make_bench_profile(GEOMETRY, {"sim": {"slm": {"two_pi_nm": 520.0, "gamma": 1.0, "zero_order": 0.0},
                                                    "beam": {"tilt_mrad": list(tilt_mrad)},
                                                    "aberration": {"green": hidden}}})
    setup = optical_setup(profile, "green")
    radius = pupil_radius_m(setup.shape, setup.pitch_m)
    tilt = {f"tilt_{axis}": radius * math.sin(angle * 1e-3) / (2 * setup.wavelength_m)
            for axis, angle in zip(("vertical", "horizontal"), tilt_mrad)}
    model = FittedOptics(tuple({**tilt, **hidden}.items()))
    amplitude, points = dot_grid_target(profile.slm.shape, profile.optics.roi, (12, 21))
    errors = {}
    for name, through in (("ideal", setup), ("fitted", dataclasses.replace(setup, field_model=model))):
        gray = slm_for(profile).encode(get_method("dpac")(amplitude, through), "green")
        fit = fit_registration(points, dots_in_capture(sim_exposure(profile, gray, {"green": POWERS_W["green"]}), 1))
        assert fit.inliers == fit.points, name
        errors[name] = corner_error(profile, fit.homography, physics.camera_homography(profile)) / 2.0
    assert errors["ideal"] > 5.0 and errors["fitted"] < 0.25 * CORNER_TOLERANCE, errors
