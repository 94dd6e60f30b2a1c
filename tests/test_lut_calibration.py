"""SLM lookup-table calibration: the grating frames, the inversion of I = a + b cos d against analytic curves
(exact where the extrema are sampled), its refusals, the monotone table, and the whole measurement on the
simulated bench against the simulator's true response (`physics.true_lut`) for red, green and blue."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest
from conftest import SMALL_BENCH, sim_exposure

from benchctl.capture.lut_calibration import (
    CalibrationError,
    calibrate_lut,
    calibration_grays,
    grating_frame,
    lut_from_response,
    phase_response,
    zero_order_signal,
)
from benchctl.capture.raw import RawImage
from benchctl.devices.sim import physics
from benchctl.profiles import Profile

# The conftest's SMALL_BENCH: a 64 x 96 SLM (8 um) imaged at 1.5 sensor pixels per SLM pixel, turned 3 degrees, behind
# the default Fourier iris (0.5 x Nyquist), with the default true response: two_pi_nm = 600, gamma 1.05, zero order
# 0.02, so the depth is 0.88 / 1.15 / 1.33 x 2 pi at 680 / 520 / 450 nm.
POWERS_W = {"red": 4e-3, "green": 2e-3, "blue": 2e-3}  # gray 0 (a plane wave) at 50-60 % of full scale
RMS_TOLERANCE_RAD = 0.01
MAX_TOLERANCE_RAD = 0.04
"""Measured table against the true one over all 256 levels (measured: RMS 0.0008 / 0.0032 / 0.0015 rad, max
0.0027 / 0.019 / 0.0065 rad for red / green / blue; the largest errors sit next to phase pi, where the signal
is flat in phase)."""


@pytest.fixture
def profile(make_bench_profile: Callable[..., Profile]) -> Profile:
    return make_bench_profile(SMALL_BENCH, setpoints_mw={"red": 4},
                              sim={"seed": 5, "imaging": {"magnification": 0.75, "rotation_deg": 3.0}})


def measured_signals(profile: Profile, channel: str, colour: int, grays: list[int],
                     homography: np.ndarray | None, power_w: float) -> list[float]:
    """Zero-order signal of each gray level's grating, one frame each (frame numbers differ: fresh noise)."""
    frames = (sim_exposure(profile, grating_frame(profile.slm.shape, gray), {channel: power_w}, frame=gray + 1)
              for gray in grays)
    return [zero_order_signal(image, colour, homography, profile.slm.shape) for image in frames]


# -- frames and gray levels ----------------------------------------------------------------------------------------


def test_calibration_grays_are_every_step_and_the_last_level() -> None:
    assert calibration_grays() == list(range(0, 256, 8)) + [255]
    assert len(calibration_grays()) == 33
    assert calibration_grays(10, 256) == [0, 256, 512, 768, 1023]
    assert calibration_grays(8, 5)[-2:] == [250, 255]
    with pytest.raises(CalibrationError, match=r"bit depth 1..16 and step >= 1, got 8 and 0"):
        calibration_grays(8, 0)


def test_grating_frame_alternates_gray_0_and_the_level_by_column() -> None:
    frame = grating_frame((4, 6), 200)
    assert frame.dtype == np.uint8
    assert frame.tolist() == [[0, 200, 0, 200, 0, 200]] * 4
    wide = grating_frame((2, 8), 1000, period_px=4, bit_depth=10)
    assert wide.dtype == np.uint16 and wide[0].tolist() == [0, 0, 1000, 1000, 0, 0, 1000, 1000]
    with pytest.raises(CalibrationError, match=r"gray 256 is outside 0..255 for a 8-bit SLM"):
        grating_frame((4, 6), 256)
    with pytest.raises(CalibrationError, match=r"even number of pixels >= 2, got 3"):
        grating_frame((4, 6), 10, period_px=3)


# -- the inversion -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("leak", [0.0, 0.02, 0.1])
def test_phase_response_inverts_an_analytic_curve_exactly(leak: float) -> None:
    """d(g) = 2 pi g / 192 (depth 2.66 pi) seen through I = (1 + f^2)/2 + (1 - f^2)/2 cos d, plus an offset and a
    gain: the extrema (d = pi at gray 96, 2 pi at 192) are sampled, so the recovered phases are exact."""
    grays = calibration_grays()
    truth = 2 * math.pi * np.array(grays) / 192
    signal = 0.01 + 0.4 * ((1 + leak**2) / 2 + (1 - leak**2) / 2 * np.cos(truth))
    assert phase_response(grays, signal) == pytest.approx(truth, abs=1e-6)


def test_phase_response_unwraps_a_curved_response_between_samples() -> None:
    """The simulator's kind of response (2.66 pi, gamma 1.05): the minimum falls between samples and is found by
    the parabola through its neighbours; every phase within 0.002 rad (measured 0.0004; the sampled minimum
    alone would be off by 0.18 rad)."""
    grays = calibration_grays()
    truth = 2 * math.pi * (600 / 450) * (np.array(grays) / 256) ** 1.05
    signal = 0.3 + 0.25 * np.cos(truth)
    phases = phase_response(grays, signal)
    assert np.abs(phases - truth).max() < 0.002
    assert (np.diff(phases) > 0).all()


def test_noise_beside_an_extremum_does_not_invent_a_turn() -> None:
    """A wiggle of 1 % of the span at the flat top of the curve (d near 2 pi) is below the turn hysteresis."""
    grays = calibration_grays()
    truth = 2 * math.pi * np.array(grays) / 160  # d = pi at gray 80, 2 pi at 160, 3.2 pi at 255
    signal = 0.5 + 0.5 * np.cos(truth)
    signal[grays.index(152)] += 0.01  # just before the maximum at 160
    phases = phase_response(grays, signal)
    assert np.abs(phases - truth).max() < 0.25  # the wiggled sample itself; the rest unaffected
    assert np.abs(np.delete(phases - truth, grays.index(152))).max() < 1e-6


def test_a_depth_below_pi_is_refused() -> None:
    grays = calibration_grays()
    truth = 0.9 * math.pi * np.array(grays) / 255
    with pytest.raises(CalibrationError, match=r"falls from 1 at gray 0 to 0\.0[0-9]+ at gray 255 without reaching "
                                               r"a minimum: the phase depth is below pi"):
        phase_response(grays, 0.5 + 0.5 * np.cos(truth))


def test_a_curve_without_modulation_is_refused() -> None:
    grays = calibration_grays()
    with pytest.raises(CalibrationError, match=r"barely changes with gray level \(0\.5 at gray 0, minimum 0\.45; "
                                               r"contrast 0\.10 < 0\.5\)"):
        phase_response(grays, 0.5 - 0.05 * np.linspace(0, 1, len(grays)))
    with pytest.raises(CalibrationError, match=r"grays must start at 0"):
        phase_response([8, 16, 24], [1.0, 0.5, 0.1])


def test_a_turn_far_from_an_extremum_is_refused() -> None:
    """A signal that falls halfway, rises and only then falls to its minimum is no cos curve of a monotonic
    phase: its first turn (gray 80, at mid-span) is not a multiple of pi."""
    grays = calibration_grays()
    signal = np.interp(grays, [0, 80, 160, 255], [1.0, 0.5, 0.8, 0.0])
    with pytest.raises(CalibrationError, match=r"turns at gray 80 at \+0\.00 of its span, too far from its minimum"):
        phase_response(grays, signal)


# -- the table -----------------------------------------------------------------------------------------------------


def test_a_linear_response_gives_the_linear_table() -> None:
    grays = calibration_grays()
    lut = lut_from_response(grays, 0.3 + 2 * math.pi * np.array(grays) / 256, bit_depth=8)  # any phase(0)
    assert lut.levels == 256
    assert np.allclose(lut.phases, np.arange(256, dtype=np.float64) * (2 * math.pi / 256), atol=1e-12)


def test_the_table_is_monotonic_and_follows_the_measured_points() -> None:
    grays = calibration_grays()
    truth = 2 * math.pi * 1.33 * (np.array(grays) / 256) ** 1.05
    noisy = truth + np.random.default_rng(0).normal(0, 0.01, len(grays))
    noisy[0] = 0.0
    lut = lut_from_response(grays, noisy, bit_depth=8)
    table = lut.phases
    assert table[0] == 0.0 and (np.diff(table) >= 0).all()
    levels = np.arange(256)
    reference = 2 * math.pi * 1.33 * (levels / 256) ** 1.05
    assert np.abs(table - reference).max() < 0.04  # noise 0.01 rad, pooled where it reversed neighbours
    with pytest.raises(CalibrationError, match=r"measured grays end at 248; a 8-bit table needs gray 255"):
        lut_from_response(grays[:-1], noisy[:-1], bit_depth=8)


# -- the simulated bench -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("channel, colour, depth", [("red", 0, 0.88), ("green", 1, 1.15), ("blue", 2, 1.33)])
def test_calibration_recovers_the_simulators_true_response(profile: Profile, channel: str, colour: int,
                                                           depth: float) -> None:
    grays = calibration_grays()
    homography = physics.camera_homography(profile)
    signals = np.array(measured_signals(profile, channel, colour, grays, homography, POWERS_W[channel]))
    true_table = physics.true_lut(profile.channel(channel).wavelength_m, 8, profile.sim.slm).phases
    assert true_table[-1] == pytest.approx(2 * math.pi * depth * (255 / 256) ** 1.05, rel=0.01)

    # The derivation's claim: the zero order follows (1 + f^2)/2 + (1 - f^2)/2 cos d exactly, leakage included.
    f = profile.sim.slm.zero_order
    model = (1 + f**2) / 2 + (1 - f**2) / 2 * np.cos(true_table[grays])
    assert signals / signals[0] == pytest.approx(model / model[0], abs=0.005)  # measured within 0.0015

    lut = calibrate_lut(grays, signals, bit_depth=8)
    error = lut.phases - true_table
    assert np.sqrt(np.mean(error**2)) < RMS_TOLERANCE_RAD
    assert np.abs(error).max() < MAX_TOLERANCE_RAD


def test_calibration_without_a_registration_reads_the_sensors_centre(profile: Profile) -> None:
    """No homography: the central half of the active area (here inside the SLM's image) gives the same table."""
    grays = calibration_grays(8, 16)
    signals = measured_signals(profile, "blue", 2, grays, None, 1.5e-3)
    lut = calibrate_lut(grays, signals, bit_depth=8)
    true_table = physics.true_lut(450e-9, 8, profile.sim.slm).phases
    error = lut.phases - true_table
    assert np.sqrt(np.mean(error**2)) < RMS_TOLERANCE_RAD and np.abs(error).max() < MAX_TOLERANCE_RAD


def test_a_saturated_grating_is_refused(profile: Profile) -> None:
    image = sim_exposure(profile, grating_frame(profile.slm.shape, 0), {"green": 20e-3}, frame=1)
    with pytest.raises(CalibrationError, match=r"<bytes>: 100\.0% of the measured region is saturated; lower the "
                                               r"exposure"):
        zero_order_signal(image, 1, physics.camera_homography(profile), profile.slm.shape)
    with pytest.raises(CalibrationError, match=r"a homography needs the SLM grid's shape"):
        zero_order_signal(image, 1, physics.camera_homography(profile))


def test_the_signal_is_the_mean_of_the_colours_pixels_in_the_central_region() -> None:
    """A mosaic whose green pixels read 0.25 and others 0.9: the green signal is 0.25 wherever it is measured."""
    mosaic = np.full((40, 60), 0.9, dtype=np.float32)
    mosaic[0::2, 1::2] = mosaic[1::2, 0::2] = 0.25
    image = RawImage(mosaic, np.array([[0, 1], [1, 2]], np.uint8), np.zeros(mosaic.shape, bool),
                     np.zeros((2, 2)), 1.0, "synthetic")
    assert zero_order_signal(image, 1) == pytest.approx(0.25)
    homography = np.array([[1.5, 0, 5], [0, 1.5, 4], [0, 0, 1]])
    assert zero_order_signal(image, 1, homography, (24, 32)) == pytest.approx(0.25)
    assert zero_order_signal(image, 0, homography, (24, 32)) == pytest.approx(0.9)
    clipped = dataclasses.replace(image, saturated=np.ones(mosaic.shape, bool))
    with pytest.raises(CalibrationError, match=r"synthetic: 100\.0% of the measured region is saturated"):
        zero_order_signal(clipped, 1)
