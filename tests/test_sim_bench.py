"""The simulated bench's camera physics against references: photometry from P t lambda / (h c), the sensor
model's noise and levels, the configured spectral response and camera geometry, a grating's deflection angle,
determinism, work only for emitting channels, real DNG files, and a DPAC hologram seen as predicted."""

from __future__ import annotations

import io
import math
import typing
from collections.abc import Callable
from pathlib import Path

import cv2
import msgspec
import numpy as np
import pytest
import rawpy
import torch
from conftest import SMALL_BENCH, bench_profile_text

import benchctl.runner.builtin
from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.setups import optical_setup
from benchctl.capture.raw import RawImage, decode_raw
from benchctl.cgh import get_method
from benchctl.devices.camera import camera_for
from benchctl.devices.laser import open_laser
from benchctl.devices.sim import physics
from benchctl.devices.sim.camera import SimCamera
from benchctl.devices.sim.state import reset_states
from benchctl.devices.slm import open_slm, slm_for
from benchctl.errors import BenchctlError
from benchctl.holograms.scene import compute_scene
from benchctl.optics import PhaseLUT, propagation
from benchctl.optics.aberration import ZERNIKE_TERMS, defocus_focal_length_m, gaussian_blur, zernike_basis
from benchctl.optics.fitted import FittedOptics
from benchctl.profiles import LaserConfig, Profile, SimConfig, ZernikeTerm, load_profile

H_PLANCK, C_LIGHT = 6.62607015e-34, 299792458.0

# The conftest's SMALL_BENCH without the iris: a 64 x 96 SLM imaged at 8 um / 4 um * 0.75 = 1.5 sensor pixels per SLM
# pixel, turned 10 degrees, onto a 176 x 256 sensor with 4 / 10 masked rows / columns. Green sees its true response
# equal to the linear table.
SIM_SMALL = {
    "optics": {"iris_fraction": None},
    "camera": {"exposure_s": 0.001, "iso": 100},
    "sim": {"seed": 7, "beam": {"efficiency": 2e-5}, "slm": {"two_pi_nm": 520.0, "gamma": 1.0, "zero_order": 0.0},
            "imaging": {"magnification": 0.75, "rotation_deg": 10.0},
            "sensor": {"read_noise_e": 5.0, "response": {"green": [0.1, 0.5, 0.05], "blue": [0.02, 0.1, 0.4]}}},
}
SCALE = 0.75 * 8.0 / 4.0  # sensor pixels per SLM pixel
GAIN_ISO100 = (16383 - 2048) / 26000.0  # DN per electron: the full well reaches the white level at base ISO


@pytest.fixture
def profile(make_bench_profile: Callable[..., Profile]) -> Profile:
    return make_bench_profile(SMALL_BENCH, SIM_SMALL)


def changed(profile: Profile, section: str, **values: object) -> Profile:
    """`profile` with keys of one section replaced: "optics" or a [sim] part ("slm", "beam", "imaging", "sensor")."""
    if section == "optics":
        return msgspec.structs.replace(profile, optics=msgspec.structs.replace(profile.optics, **values))
    part = msgspec.structs.replace(getattr(profile.sim, section), **values)
    return msgspec.structs.replace(profile, sim=msgspec.structs.replace(profile.sim, **{section: part}))


def capture(profile: Profile, gray: np.ndarray | None, powers_mw: dict[str, float], **settings: float) -> RawImage:
    """Show `gray` on the simulated SLM, switch the lasers as given (others off), capture one DNG, decode it."""
    with open_slm(profile) as slm, open_laser(profile) as laser:
        if gray is not None:
            slm.show_gray(gray)
        for name, mw in powers_mw.items():
            laser.set_power(name, mw * 1e-3)
            laser.set_emission(name, True)
        config = msgspec.structs.replace(profile.camera, **settings)
        with SimCamera(config, profile) as camera:
            return decode_raw(camera.capture()[0].data)


def to_sensor(profile: Profile, x: float, y: float) -> np.ndarray:
    """Where target-plane pixel (x = col, y = row) should land in the active area, from the documented geometry:
    the grid centre at the active area's centre plus offset, scaled by SCALE, turned clockwise as displayed."""
    sensor, imaging = profile.sim.sensor, profile.sim.imaging
    rows, cols = sensor.shape[0] - sensor.margin[0], sensor.shape[1] - sensor.margin[1]
    angle = math.radians(imaging.rotation_deg)
    dx, dy = x - (profile.slm.width - 1) / 2, y - (profile.slm.height - 1) / 2
    return np.array([(cols - 1) / 2 + imaging.offset_px[1] + SCALE * (dx * math.cos(angle) - dy * math.sin(angle)),
                     (rows - 1) / 2 + imaging.offset_px[0] + SCALE * (dx * math.sin(angle) + dy * math.cos(angle))])


def colour_mask(image: RawImage, colour: int) -> np.ndarray:
    """Pixels of the visible mosaic whose filter is `colour` (0 R, 1 G, 2 B), from the file's CFA pattern."""
    rows, cols = np.indices(image.mosaic.shape)
    return image.cfa[rows % 2, cols % 2] == colour


def central_region(profile: Profile, shape: tuple[int, int]) -> np.ndarray:
    """Sensor pixels whose target-plane point lies in the central half of the SLM grid (both axes)."""
    inverse = np.linalg.inv(physics.camera_homography(profile))
    rows, cols = np.indices(shape)
    x, y, _ = inverse @ np.stack([cols.ravel(), rows.ravel(), np.ones(rows.size)])
    h, w = profile.slm.shape
    inside = (abs(x - (w - 1) / 2) < w / 4) & (abs(y - (h - 1) / 2) < h / 4)
    return inside.reshape(shape)


def predicted_electrons(profile: Profile, channel: str, power_w: float, exposure_s: float) -> float:
    """Mean photo-electrons per sensor pixel of a plane wave filling the SLM (before the filter's efficiency)."""
    wavelength = profile.channel(channel).wavelength_m
    photons = power_w * exposure_s * wavelength / (H_PLANCK * C_LIGHT) * profile.sim.beam.efficiency
    return photons / (profile.slm.height * profile.slm.width) / SCALE**2


# -- the sensor ----------------------------------------------------------------------------------------------


def test_dark_frame_is_black_level_plus_read_noise(profile: Profile) -> None:
    with SimCamera(profile.camera, profile) as camera:
        frame = camera.capture()[0]
    with rawpy.imread(io.BytesIO(frame.data)) as raw:
        counts = raw.raw_image.astype(np.float64)  # the whole frame, masked margins included
    gain = GAIN_ISO100
    assert counts.shape == (176, 256)
    expected_std = math.hypot(5.0 * gain, math.sqrt(1 / 12))  # read noise, plus rounding to whole counts
    assert counts.mean() == pytest.approx(2048, abs=4 * expected_std / math.sqrt(counts.size))
    assert counts.std() == pytest.approx(expected_std, rel=0.03)


def test_iso_scales_the_read_noise_in_counts(profile: Profile) -> None:
    image = capture(profile, None, {}, iso=800)
    assert image.mosaic.std() * (16383 - 2048) == pytest.approx(5.0 * GAIN_ISO100 * 8, rel=0.03)


@pytest.mark.parametrize("channel, colour, efficiency", [("green", 1, 0.5), ("blue", 2, 0.4)])
def test_plane_wave_gives_the_predicted_uniform_signal(profile: Profile, channel: str, colour: int,
                                                       efficiency: float) -> None:
    """Gray 0 everywhere: a plane wave, so every target pixel receives P / (H W); the sensor pixels of the
    channel's main colour then hold that many photons / SCALE^2 each, times their efficiency and the gain."""
    profile = changed(profile, "optics", distance_mm=1.0)  # edge ringing stays near the grid's border
    image = capture(profile, np.zeros((64, 96), np.uint8), {channel: 2.0})
    electrons = predicted_electrons(profile, channel, 2e-3, 0.001) * efficiency
    assert 2000 < electrons < 20000  # a well-exposed test: shot noise ~1 %, far above read noise
    region = central_region(profile, image.mosaic.shape) & colour_mask(image, colour)
    signal = image.mosaic[region] * (16383 - 2048) / GAIN_ISO100  # back to electrons
    assert signal.mean() == pytest.approx(electrons, rel=0.005)  # measured within 0.07 %
    assert signal.std() == pytest.approx(math.sqrt(electrons), rel=0.1)  # uniform: only shot noise


def test_a_gaussian_beam_peaks_at_its_analytic_irradiance(profile: Profile) -> None:
    """Waist w: the centre of the beam carries 2 / (pi w^2) of the power per unit area."""
    profile = changed(changed(profile, "optics", distance_mm=1.0), "beam", waist_mm=0.2)
    image = capture(profile, np.zeros((64, 96), np.uint8), {"green": 2.0})
    fraction = 2 / (math.pi * 0.2e-3**2) * 8e-6**2  # of the beam's power on the central target pixel
    electrons = predicted_electrons(profile, "green", 2e-3, 0.001) * 64 * 96 * fraction * 0.5
    rows, cols = np.indices(image.mosaic.shape)
    centre = to_sensor(profile, 47.5, 31.5)
    near = (np.hypot(cols - centre[0], rows - centre[1]) < 1.5 * SCALE) & colour_mask(image, 1)
    signal = image.mosaic[near] * (16383 - 2048) / GAIN_ISO100
    assert signal.mean() == pytest.approx(electrons, rel=0.02)


@pytest.mark.parametrize("cfa", ["RGGB", "GBRG"])
def test_spectral_response_puts_the_configured_fractions_into_each_colour(profile: Profile, cfa: str) -> None:
    profile = changed(changed(profile, "optics", distance_mm=1.0), "sensor", cfa=cfa)
    image = capture(profile, np.zeros((64, 96), np.uint8), {"green": 2.0})
    assert image.layout == cfa
    region = central_region(profile, image.mosaic.shape)
    means = [image.mosaic[region & colour_mask(image, colour)].mean() for colour in range(3)]
    assert means[0] / means[1] == pytest.approx(0.1 / 0.5, rel=0.02)
    assert means[2] / means[1] == pytest.approx(0.05 / 0.5, rel=0.03)


def test_light_lands_only_on_the_image_of_the_slm_grid(profile: Profile) -> None:
    profile = changed(profile, "optics", distance_mm=1.0)
    image = capture(profile, np.zeros((64, 96), np.uint8), {"green": 0.3})
    assert not image.saturated.any()
    inverse = np.linalg.inv(physics.camera_homography(profile))
    rows, cols = np.indices(image.mosaic.shape)
    x, y, _ = inverse @ np.stack([cols.ravel(), rows.ravel(), np.ones(rows.size)])
    outside = ((x < -3) | (x > 98) | (y < -3) | (y > 66)).reshape(rows.shape)
    assert outside.mean() > 0.3
    dark = image.mosaic[outside] * (16383 - 2048)
    assert abs(dark.mean()) < 0.2 and dark.std() == pytest.approx(math.hypot(5 * GAIN_ISO100, 0.29), rel=0.05)


def test_saturation_clips_at_the_white_level(profile: Profile) -> None:
    profile = changed(profile, "optics", distance_mm=1.0)
    image = capture(profile, np.zeros((64, 96), np.uint8), {"green": 2.0}, exposure_s=0.2)
    lit = central_region(profile, image.mosaic.shape) & colour_mask(image, 1)
    assert predicted_electrons(profile, "green", 2e-3, 0.2) * 0.5 > 10 * 26000
    assert np.all(image.mosaic[lit] == 1.0) and np.all(image.saturated[lit])
    assert image.mosaic.max() == 1.0


# -- the geometry ----------------------------------------------------------------------------------------------


def test_homography_maps_points_as_configured(profile: Profile) -> None:
    homography = physics.camera_homography(profile)
    for x, y in [(47.5, 31.5), (0, 0), (95, 0), (20, 50)]:
        mapped = homography @ [x, y, 1]
        assert mapped[:2] / mapped[2] == pytest.approx(to_sensor(profile, x, y), abs=1e-9)


def spot_centroid(image: RawImage, around: np.ndarray, radius: float) -> np.ndarray:
    """Intensity centroid (x, y) of the green pixels within `radius` of `around`."""
    rows, cols = np.indices(image.mosaic.shape)
    window = colour_mask(image, 1) & (np.hypot(cols - around[0], rows - around[1]) < radius)
    weights = np.where(window, image.mosaic, 0.0)
    return np.array([(weights * cols).sum(), (weights * rows).sum()]) / weights.sum()


@pytest.mark.parametrize("period", [(0, 0), (0, 8), (16, 8), (-16, 0)])
def test_a_blazed_grating_moves_the_spot_by_its_diffraction_angle(profile: Profile,
                                                                  period: tuple[int, int]) -> None:
    """A Gaussian spot on a blazed grating of period P pixels leaves at sin(theta) = lambda / (P pitch): at the
    target plane it has moved by z tan(theta); the camera shows it where the configured geometry maps that."""
    profile = changed(profile, "beam", waist_mm=0.064)
    rows, cols = np.indices((64, 96))
    ramp = sum((rows, cols)[axis] / p for axis, p in enumerate(period) if p)
    gray = (np.floor(np.remainder(ramp, 1.0) * 256) if period != (0, 0) else np.zeros((64, 96))).astype(np.uint8)
    image = capture(profile, gray, {"green": 2.0})
    target = [(96 - 1) / 2, (64 - 1) / 2]  # (x, y): the beam's centre
    for axis, p in ((1, period[1]), (0, period[0])):
        if p:
            sin_theta = 520e-9 / (p * 8e-6)
            target[1 - axis] += 20e-3 * sin_theta / math.sqrt(1 - sin_theta**2) / 8e-6
    expected = to_sensor(profile, *target)
    assert spot_centroid(image, expected, radius=25) == pytest.approx(expected, abs=1.0)


# -- what is computed ------------------------------------------------------------------------------------------


def test_only_emitting_channels_are_propagated(profile: Profile, monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    original = propagation.Propagator.__call__

    def counted(self: propagation.Propagator, field: torch.Tensor) -> torch.Tensor:
        calls.append(self.plan.wavelength_m)
        return original(self, field)

    monkeypatch.setattr(propagation.Propagator, "__call__", counted)
    gray = np.zeros((64, 96), np.uint8)
    dark = capture(profile, gray, {})
    assert calls == []
    assert abs(dark.mosaic.mean()) < 1e-3  # nothing but noise around black
    capture(profile, gray, {"green": 2.0})
    assert calls == [pytest.approx(520e-9)]
    calls.clear()
    capture(profile, gray, {"red": 1.0, "green": 2.0, "blue": 2.0})
    assert sorted(calls) == pytest.approx([450e-9, 520e-9, 680e-9])


def rgb_profile(profile: Profile, dialect: str) -> Profile:
    """`profile` with its three channels on simulated units of `dialect`: one template unit, one head per port
    (cobolt, obis), or an OBIS box with three heads on one port."""
    channels = profile.channels
    if dialect == "template":
        return profile
    if dialect == "obis-box":
        laser = LaserConfig(channels=channels, driver="obis", port="sim://obis-box?dialect=obis&channels=3")
    else:
        laser = LaserConfig(channels=tuple(msgspec.structs.replace(ch, port=f"sim://{dialect}-{ch.name}?dialect={dialect}")
                                           for ch in channels), driver=dialect)
    return msgspec.structs.replace(profile, laser=laser)


@pytest.mark.parametrize("dialect", ["template", "cobolt", "obis", "obis-box"])
def test_emitting_channels_are_read_from_each_units_state(profile: Profile, dialect: str) -> None:
    profile = rgb_profile(profile, dialect)
    with open_laser(profile) as laser:
        laser.set_power("green", 1e-3)
        laser.set_power("blue", 3e-3)
        laser.set_emission("blue", True)
        assert physics.emitting_channels(profile) == {"blue": pytest.approx(3e-3)}
    assert physics.emitting_channels(profile) == {}  # closing turned emission off


def test_a_real_laser_port_is_refused(profile: Profile) -> None:
    laser = msgspec.structs.replace(profile.laser, port="/dev/ttyUSB0")
    with pytest.raises(BenchctlError, match=r"'red' is on /dev/ttyUSB0, not a sim:// port"):
        physics.emitting_channels(msgspec.structs.replace(profile, laser=laser))


def test_frames_repeat_for_a_seed_and_differ_from_frame_to_frame(profile: Profile) -> None:
    gray = np.zeros((64, 96), np.uint8)
    first = [capture(profile, gray, {"green": 2.0}).mosaic for _ in range(2)]
    assert not np.array_equal(first[0], first[1])  # frame 1 and frame 2
    reset_states()  # a fresh bench: the frame counter starts again
    again = capture(profile, gray, {"green": 2.0}).mosaic
    assert np.array_equal(again, first[0])
    other_seed = msgspec.structs.replace(profile, sim=msgspec.structs.replace(profile.sim, seed=8))
    reset_states()
    assert not np.array_equal(capture(other_seed, gray, {"green": 2.0}).mosaic, first[0])


# -- the files -------------------------------------------------------------------------------------------------


def test_captures_are_dngs_rawpy_reads_with_the_settings(profile: Profile, tmp_path: Path) -> None:
    config = msgspec.structs.replace(profile.camera, exposure_s=0.004, iso=400)
    with SimCamera(config, profile) as camera:
        assert camera.identity()["model"] == "Canon EOS M10 (benchctl simulation)"
        frames = camera.capture(tmp_path, frames=2)
    assert [f.file_name for f in frames] == ["IMG_0001.DNG", "IMG_0002.DNG"]
    assert frames[1].metadata["frame"] == 2 and frames[1].metadata["seed"] == 7
    assert frames[0].metadata["lasers_on_w"] == {} and frames[0].metadata["slm_frame"] is None
    with rawpy.imread(str(frames[0].path)) as raw:
        assert raw.raw_image.shape == (176, 256)
        assert (raw.sizes.top_margin, raw.sizes.left_margin) == (4, 10)
        assert raw.raw_image_visible.shape == (172, 246)
        assert list(raw.black_level_per_channel) == [2048] * 4 and raw.white_level == 16383
        assert raw.other.iso_speed == 400 and raw.other.shutter_speed == pytest.approx(0.004)


def test_the_body_settings_apply_where_the_camera_section_gives_none(profile: Profile) -> None:
    frame = physics.render_capture(profile)
    assert (frame.metadata["exposure_s"], frame.metadata["iso"]) == (0.01, 100)


# -- the SLM and the whole chain -------------------------------------------------------------------------------


def test_true_response_is_linear_only_where_configured(profile: Profile) -> None:
    assert np.allclose(physics.true_lut(520e-9, 8, profile.sim.slm).phases, PhaseLUT.linear(8).phases, rtol=1e-12)
    default = physics.true_lut(520e-9, 8, SimConfig().slm).phases
    assert float(default[128]) == pytest.approx(2 * math.pi * 600 / 520 * 0.5**1.05)


def test_a_dpac_hologram_is_seen_as_benchctl_predicts(profile: Profile) -> None:
    """A DPAC hologram of a letter, displayed through the profile's table and lit in green: the camera's green
    plane, registered with the known geometry, correlates with benchctl's own simulated reconstruction of the
    displayed frame at 0.995 (measured; noise and the camera's resampling make the rest); the mirrored
    prediction correlates at 0.53."""
    profile = changed(profile, "optics", iris_fraction=0.5)
    setup = optical_setup(profile, "green")
    letter = np.zeros(setup.shape, np.float32)  # an "F": no symmetry, so a mirrored image cannot match
    letter[12:52, 30:38] = letter[12:20, 30:66] = letter[28:35, 30:58] = 1.0
    target = torch.from_numpy(letter)
    phase = get_method("dpac")(target, setup)
    with open_slm(profile) as slm:
        gray = slm.show_phase(phase, "green")
        predicted = setup.reconstruct(torch.from_numpy(slm.decode(gray, "green"))).square().numpy()
    with open_laser(profile) as laser:
        laser.set_power("green", 2e-3)
        laser.set_emission("green", True)
        with SimCamera(msgspec.structs.replace(profile.camera, exposure_s=0.004), profile) as camera:
            image = decode_raw(camera.capture()[0].data)
    green = image.planes()[1]  # cell (i, j) is centred on visible pixel (2 i + 0.5, 2 j + 0.5)
    to_plane = np.array([[0.5, 0, -0.25], [0, 0.5, -0.25], [0, 0, 1]]) @ physics.camera_homography(profile)
    registered = cv2.warpAffine(green, to_plane[:2], (96, 64), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    roi = setup.roi_slices

    def correlation(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.corrcoef(a[roi].ravel(), b[roi].ravel())[0, 1])

    assert registered[roi].max() < 0.8  # well exposed, nothing clipped
    assert correlation(registered, predicted) > 0.98
    assert correlation(registered, predicted[:, ::-1]) < 0.7


# -- the [sim] section of a profile ----------------------------------------------------------------------------


def test_simulated_profile_lists_the_defaults() -> None:
    profile = load_profile("simulated")
    assert profile.sim == SimConfig()
    assert profile.camera.driver == "sim"


def test_a_profile_without_sim_section_gets_the_defaults(small_profile_path: Path) -> None:
    assert load_profile(small_profile_path).sim == SimConfig()


@pytest.mark.parametrize("block, message", [
    ("[sim.sensor]\nshape = [176, 256]\nmargin = [3, 10]\n", r"sim\.sensor\.margin: rows margin 3 must be even"),
    ("[sim.sensor]\nblack_level = 20000\n", r"sim\.sensor\.black_level: 20000 is not below the white level 16383"),
    ("[sim.sensor.response]\npurple = [0.1, 0.2, 0.3]\n", r"sim\.sensor\.response\.purple: no laser channel"),
    ("[sim.sensor.response]\nred = [0.1, 0.2]\n", r"sim\.sensor\.response\.red: expected three numbers"),
    ("[sim.sensor.response]\nred = [0.1, -0.2, 0.3]\n", r"sim\.sensor\.response\.red\[1\]: must be >= 0"),
    ("[sim.sensor]\ncfa = \"RGBG\"\n", r"sim\.sensor\.cfa: unknown value 'RGBG'"),
    ("[sim.imaging]\nmagnifcation = 2\n", r"sim\.imaging\.magnifcation: unknown key \(did you mean 'magnification'"),
])
def test_sim_section_errors_name_the_key(tmp_path: Path, block: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(bench_profile_text(SMALL_BENCH, SIM_SMALL, sim=None) + "[sim]\n" + block)
    with pytest.raises(BenchctlError, match=message) as info:
        load_profile(path)
    assert str(path) in str(info.value)


# -- optics that differ from the model ([sim.aberration], beam offset / tilt, crosstalk, stray light) -----------


def irradiance(profile: Profile, gray: np.ndarray, channel: str = "green") -> np.ndarray:
    """The simulator's target-plane irradiance (fraction of the beam's power per pixel) of `gray`, noiseless."""
    return physics._target_irradiance(profile, profile.channel(channel), gray).numpy()


def moments(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid (row, col) and variance (rows, cols) of an irradiance image in pixels."""
    rows, cols = np.indices(image.shape)
    total = image.sum()
    centre = np.array([(image * rows).sum(), (image * cols).sum()]) / total
    variance = np.array([(image * (rows - centre[0]) ** 2).sum(), (image * (cols - centre[1]) ** 2).sum()]) / total
    return centre, variance


def test_zernike_terms_are_the_ansi_polynomials() -> None:
    """The RMS-normalised ANSI/OSA terms against their closed forms at the pixel centres of a 3 x 4 panel (the unit
    disc circumscribes the panel; theta from +x = columns towards +y = rows)."""
    basis = dict(zip(ZERNIKE_TERMS, zernike_basis((3, 4), 1e-6).numpy()))
    y, x = np.indices((3, 4)) - np.array([1.0, 1.5])[:, None, None]
    rho, theta = np.hypot(y, x) / (np.hypot(3, 4) / 2), np.arctan2(y, x)
    expected = {"astigmatism_oblique": math.sqrt(6) * rho**2 * np.sin(2 * theta),
                "defocus": math.sqrt(3) * (2 * rho**2 - 1),
                "astigmatism_vertical": math.sqrt(6) * rho**2 * np.cos(2 * theta),
                "coma_vertical": math.sqrt(8) * (3 * rho**3 - 2 * rho) * np.sin(theta),
                "coma_horizontal": math.sqrt(8) * (3 * rho**3 - 2 * rho) * np.cos(theta),
                "spherical": math.sqrt(5) * (6 * rho**4 - 6 * rho**2 + 1)}
    for name, values in expected.items():
        assert basis[name] == pytest.approx(values, abs=1e-12), name


@pytest.mark.parametrize("waves", [0.0, 0.5, -0.5])
def test_defocus_moves_the_best_focus_as_its_thin_lens_predicts(profile: Profile, waves: float) -> None:
    """A Gaussian beam (waist w0 = 0.12 mm) on a lens pattern of focal length 20 mm, plus `waves` of defocus: a
    thin lens of focal length f = -R^2 / (4 sqrt(3) c lambda) in contact, so the lens is F = 1 / (1/20 mm + 1/f).
    A Gaussian beam focused by F has its waist at d = F / (1 + (F / z_R)^2), z_R = pi w0^2 / lambda; the spot's
    second moment w^2(z) is a parabola in z whose vertex is d. c = +-0.5 moves it from 19.00 mm to 22.36 / 16.47 mm."""
    profile = changed(profile, "beam", waist_mm=0.12)
    sim = msgspec.structs.replace(profile.sim, aberration={"green": {"defocus": waves}})
    profile = msgspec.structs.replace(profile, sim=sim)
    wavelength, pitch = 520e-9, 8e-6
    y, x = (np.indices((64, 96)) - np.array([31.5, 47.5])[:, None, None]) * pitch
    lens = np.remainder(-math.pi * (x**2 + y**2) / (wavelength * 20e-3), 2 * math.pi)
    gray = np.floor(lens / (2 * math.pi) * 256 + 0.5).astype(np.int64) % 256
    focal = 1 / (1 / 20e-3 + (1 / defocus_focal_length_m(waves, wavelength, (64, 96), pitch) if waves else 0.0))
    rayleigh = math.pi * 0.12e-3**2 / wavelength
    waist_at = focal / (1 + (focal / rayleigh) ** 2)
    distances = waist_at + np.linspace(-4e-3, 4e-3, 9)
    spot = [moments(irradiance(changed(profile, "optics", distance_mm=z * 1e3), gray))[1].sum() for z in distances]
    a, b, _ = np.polyfit(distances, spot, 2)
    assert -b / (2 * a) == pytest.approx(waist_at, abs=0.1e-3)
    assert waist_at * 1e3 == pytest.approx({0.0: 19.0, 0.5: 22.36, -0.5: 16.47}[waves], abs=0.01)


def test_a_tilted_beam_moves_the_image_by_z_tan_theta(profile: Profile) -> None:
    """Tilt (2, -3) mrad over 20 mm: the beam's image moves 20 mm x tan(theta) / 8 um = (5.0, -7.5) pixels."""
    profile = changed(profile, "beam", waist_mm=0.1)
    flat = np.zeros((64, 96), np.int64)
    before = moments(irradiance(profile, flat))[0]
    after = moments(irradiance(changed(profile, "beam", waist_mm=0.1, tilt_mrad=(2.0, -3.0)), flat))[0]
    expected = np.array([20e-3 * math.tan(2e-3), 20e-3 * math.tan(-3e-3)]) / 8e-6
    assert after - before == pytest.approx(expected, abs=0.02)


def test_a_gaussian_beam_is_captured_with_its_waist_and_offset(profile: Profile) -> None:
    """1 mm from the SLM a flat phase shows the beam itself: captured, mapped back to the target plane through the
    known geometry, its centroid is the offset and its per-axis standard deviation is w / 2 (I ~ exp(-2 r^2 / w^2))."""
    profile = changed(changed(profile, "optics", distance_mm=1.0), "beam", waist_mm=0.1, offset_mm=(0.05, -0.08))
    image = capture(profile, np.zeros((64, 96), np.uint8), {"green": 0.3})
    assert not image.saturated.any()
    inverse = np.linalg.inv(physics.camera_homography(profile))
    rows, cols = np.indices(image.mosaic.shape)
    x, y, _ = inverse @ np.stack([cols.ravel(), rows.ravel(), np.ones(rows.size)])
    inside = (abs(x - 47.5) < 44) & (abs(y - 31.5) < 28)
    weights = np.where(colour_mask(image, 1).ravel() & inside, image.mosaic.ravel(), 0.0)
    centre = np.array([(weights * y).sum(), (weights * x).sum()]) / weights.sum()
    sigma = np.sqrt([(weights * (y - centre[0]) ** 2).sum(), (weights * (x - centre[1]) ** 2).sum()] / weights.sum())
    assert centre - [31.5, 47.5] == pytest.approx([0.05e-3 / 8e-6, -0.08e-3 / 8e-6], abs=0.1)
    assert 2 * sigma * 8e-6 == pytest.approx([0.1e-3, 0.1e-3], rel=0.02)


@pytest.mark.parametrize("sigma_px", [0.0, 0.6, 1.0])
def test_crosstalk_lowers_a_fine_gratings_efficiency_as_predicted(profile: Profile, sigma_px: float) -> None:
    """A period-4 sinusoidal phase grating pi + m sin(2 pi x / 4) (m = 2 pi 98 / 256, near J0's zero): blurred by
    a Gaussian of sigma pixels its modulation becomes m' = m exp(-2 pi^2 sigma^2 / 16), and the zero order of the
    four pixel phases (pi, pi + m', pi, pi - m') holds ((1 + cos m') / 2)^2 of the light. An iris at 0.3 x Nyquist
    passes only the zero order (the first orders sit at 0.5), so the power reaching the target plane, relative to
    a flat phase, is that fraction: 1.7 % sharp, 26 % at sigma = 0.6 px. (A Gaussian beam, so that no edge
    diffraction of the first orders leaks through the iris.)"""
    profile = changed(changed(profile, "optics", iris_fraction=0.3), "slm", crosstalk_px=sigma_px)
    profile = changed(profile, "beam", waist_mm=0.1)
    gray = np.broadcast_to(np.array([128, 226, 128, 30] * 24), (64, 96))
    modulation = 2 * math.pi * 98 / 256 * math.exp(-2 * math.pi**2 * sigma_px**2 / 16)
    zero_order = ((1 + math.cos(modulation)) / 2) ** 2
    ratio = irradiance(profile, gray).sum() / irradiance(profile, np.zeros((64, 96), np.int64)).sum()
    assert ratio == pytest.approx(zero_order, rel=0.01, abs=1e-4)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_blur_scales_a_sinusoid_by_its_analytic_response(dtype: torch.dtype) -> None:
    """A sinusoid of f cycles per pixel blurred by a Gaussian of variance s^2 keeps its form, its amplitude times
    exp(-2 pi^2 s^2 f^2): to float32 precision when given float32 (computed in it: the crosstalk blur on every
    model evaluation of SGD and CITL), to float64 precision when given float64 (the fit)."""
    y, x = torch.meshgrid(torch.arange(48, dtype=torch.float64), torch.arange(64, dtype=torch.float64), indexing="ij")
    fy, fx, variance = 5 / 48, 12 / 64, 0.7**2
    wave = 3.0 + 2.0 * torch.cos(2 * math.pi * (fy * y + fx * x) + 0.4)
    expected = 3.0 + 2.0 * math.exp(-2 * math.pi**2 * variance * (fy**2 + fx**2)) * (wave - 3.0) / 2.0
    blurred = gaussian_blur(wave.to(dtype)[None], variance)[0]
    assert blurred.dtype == dtype
    tolerance = 2e-6 if dtype == torch.float32 else 1e-12
    assert float((blurred.double() - expected).abs().max()) < tolerance


def test_the_blur_and_the_fitted_panel_run_on_the_device_of_their_input() -> None:
    """A GPU computes the crosstalk blur of CITL's and training's model where the phase is: every tensor the blur
    and the fitted panel make must follow their input's device (the meta device stands in for a GPU here: mixing
    it with a CPU tensor fails as CUDA would)."""
    phase = torch.zeros(2, 48, 64, device="meta")
    assert gaussian_blur(phase, 0.3).device.type == "meta"
    panel = FittedOptics(crosstalk_px=0.05, zero_order=0.02)
    modulated = panel.modulated(phase)
    assert modulated.device.type == "meta" and modulated.shape == (2, 48, 64) and modulated.is_complex()


def test_stray_light_spreads_its_fraction_evenly(profile: Profile) -> None:
    flat = np.zeros((64, 96), np.int64)
    clean = irradiance(changed(profile, "beam", waist_mm=0.1), flat)
    glare = irradiance(changed(changed(profile, "beam", waist_mm=0.1), "imaging", stray_light=0.1), flat)
    assert glare.sum() == pytest.approx(clean.sum(), rel=1e-9)
    assert glare - 0.9 * clean == pytest.approx(np.full(clean.shape, 0.1 * clean.mean()), rel=1e-6)


def test_generation_never_reads_the_hidden_optics(make_bench_profile: Callable[..., Profile]) -> None:
    """The same hologram (SGD, the reconstruction and its scores too) with and without every hidden term: the
    aberrations, beam, crosstalk and stray light live in [sim], which only the simulated camera reads."""
    hidden = {"sim": {"aberration": {"green": {"defocus": 0.4, "coma_horizontal": -0.2}},
                      "beam": {"waist_mm": 0.3, "offset_mm": [0.05, 0.0], "tilt_mrad": [0.1, 0.2]},
                      "slm": {"crosstalk_px": 0.7}, "imaging": {"stray_light": 0.02}}}
    target = torch.zeros(3, 64, 96)
    target[1, 20:44, 30:66] = 1.0
    benches = [Calibrated(make_bench_profile(SMALL_BENCH, SIM_SMALL, *extra)) for extra in ((), (hidden,))]
    results = [compute_scene(target, bench, "sgd", iterations=5, colours=["green"]) for bench in benches]
    plain, aberrated = (next(c for c in result.colours if c.channel == "green") for result in results)
    assert plain.gray is not None and np.array_equal(plain.gray, aberrated.gray)
    assert results[0].merged_scores == results[1].merged_scores


def test_aberration_entries_name_laser_channels_and_terms(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    text = bench_profile_text(SMALL_BENCH, SIM_SMALL, sim=None) + "[sim.aberration.green]\ndefocus = 0.2\n"
    path.write_text(text)
    assert load_profile(path).sim.aberration == {"green": {"defocus": 0.2}}
    for block, message in [("[sim.aberration.purple]\ndefocus = 0.1\n", r"sim\.aberration\.purple: no laser channel"),
                           ("[sim.aberration.green]\ndefocuss = 0.1\n",
                            r"sim\.aberration\.green\.defocuss: unknown key \(did you mean 'defocus'"),
                           ("[sim.aberration.green]\ncoma_vertical = \"a\"\n",
                            r"sim\.aberration\.green\.coma_vertical: expected a finite number")]:
        path.write_text(bench_profile_text(SMALL_BENCH, SIM_SMALL, sim=None) + block)
        with pytest.raises(BenchctlError, match=message):
            load_profile(path)


def test_schema_terms_are_the_optics_terms() -> None:
    assert typing.get_args(ZernikeTerm) == tuple(ZERNIKE_TERMS)


def test_the_aberrated_profile_is_the_simulated_bench_with_hidden_optics() -> None:
    plain, aberrated = load_profile("simulated"), load_profile("simulated-aberrated")
    for section in ("optics", "slm", "laser", "camera"):
        assert getattr(aberrated, section) == getattr(plain, section), section
    assert plain.sim.aberration == {} and plain.sim.slm.crosstalk_px == 0 and plain.sim.beam.tilt_mrad == (0, 0)
    assert {name: set(terms) for name, terms in aberrated.sim.aberration.items()} == {
        name: {term for term, (n, _) in ZERNIKE_TERMS.items() if n >= 2} for name in ("red", "green", "blue")}
    assert all(v != 0 for v in aberrated.sim.beam.tilt_mrad)  # the tilt is the beam's
    assert aberrated.sim.beam.waist_mm > 0 and aberrated.sim.slm.crosstalk_px > 0


def test_simulated_devices_report_their_ground_truth_and_real_ones_none(profile: Profile) -> None:
    # What calibration procedures compare against, asked of the device (procedures never import the simulator).
    slm, camera = slm_for(profile), camera_for(profile)
    green = profile.channel("green").wavelength_m
    np.testing.assert_array_equal(slm.ground_truth_lut(green),
                                  physics.true_lut(green, slm.bit_depth, profile.sim.slm).phases)
    assert slm.ground_truth_lut(green)[-1] != slm.ground_truth_lut(profile.channel("red").wavelength_m)[-1]
    np.testing.assert_array_equal(camera.ground_truth_homography(), physics.camera_homography(profile))
    real = load_profile("paper_bench")  # a framebuffer SLM
    assert slm_for(real).ground_truth_lut(green) is None
    for driver in ("ptp", "gphoto2"):
        real = msgspec.structs.replace(profile, camera=msgspec.structs.replace(profile.camera, driver=driver))
        assert camera_for(real).ground_truth_homography() is None, driver


def test_builtin_procedures_never_import_the_simulator() -> None:
    folder = Path(benchctl.runner.builtin.__file__).parent
    for path in sorted(folder.rglob("*.py")):
        assert "devices.sim" not in path.read_text(), path
