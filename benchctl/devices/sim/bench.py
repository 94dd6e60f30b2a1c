"""The simulated bench's camera physics: what a real sensor would record from the simulated SLM and lasers.

Per capture, for every laser channel that emits (and only those): the gray frame the simulated SLM shows
becomes a phase through the simulator's own response ([sim.slm], deliberately not the profile's lookup table),
lit by the laser's power (uniform, or a Gaussian beam), with a little unmodulated light from the pixel gaps;
it is propagated to the target plane by the same Propagator the holograms are computed with, at the profile's
geometry (`OpticalSetup.of(profile.geometry(...)).target_propagator()`, Fourier iris included), and becomes
photons (P t lambda / (h c) times the optical efficiency). The three colour planes of electrons (each channel's
photons times its [R, G, B] quantum efficiency) are carried onto the sensor by the camera homography
(magnification, rotation, offset; energy conserving) into only the box of sensor pixels the grid's image
covers. The sensor adds shot noise (Poisson, electrons), read noise (Gaussian, electrons), the ISO gain,
the black level, clipping at the white level and integer quantisation; masked margins and unlit pixels get
black level plus read noise only. docs/simulated_bench.md describes the model and its parameters.
"""

from __future__ import annotations

import functools
import math
from collections import Counter
from collections.abc import Mapping
from datetime import datetime

import cv2
import numpy as np
import torch
from serial.serialutil import SerialException

from benchctl.dng import CFA_LAYOUTS, dng_bytes
from benchctl.devices.camera.base import RawFrame
from benchctl.devices.errors import DeviceError
from benchctl.devices.sim.protocol_sim import parse_url
from benchctl.devices.sim.state import CAMERA_STATE, load_state, save_state
from benchctl.devices.slm.sim import read_displayed
from benchctl.optics import PhaseLUT, Propagator, gray_to_phase
from benchctl.optics.aberration import crosstalk_blur, gaussian_beam_power, tilt_phase, wavefront_phase
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import LaserChannel, Profile, SimSensorConfig, SimSLMConfig

PLANCK_J_S = 6.62607015e-34
LIGHT_M_S = 299792458.0

# A typical Bayer sensor's quantum efficiency behind its colour filters and IR-cut filter (electrons per photon):
# wavelength nm, R, G, B. Channels without a [sim.sensor.response] entry use it, interpolated linearly.
TYPICAL_QE = np.array([
    (400.0, 0.02, 0.03, 0.22),
    (450.0, 0.02, 0.10, 0.42),
    (500.0, 0.03, 0.36, 0.28),
    (550.0, 0.07, 0.46, 0.06),
    (600.0, 0.36, 0.17, 0.02),
    (650.0, 0.28, 0.05, 0.02),
    (700.0, 0.04, 0.02, 0.01),
])


@functools.lru_cache(maxsize=8)
def true_lut(wavelength_m: float, bit_depth: int, response: SimSLMConfig) -> PhaseLUT:
    """The simulated panel's real gray -> phase table at one wavelength (what calibration should measure):
    2 pi (two_pi_nm / wavelength) (g / 2^bit_depth)^gamma."""
    depth = 2 * math.pi * response.two_pi_nm * 1e-9 / wavelength_m
    levels = np.arange(1 << bit_depth, dtype=np.float64) / (1 << bit_depth)
    return PhaseLUT(depth * levels**response.gamma)


def spectral_response(profile: Profile, channel: LaserChannel) -> np.ndarray:
    """[R, G, B] quantum efficiency of the sensor's filter colours at `channel`'s wavelength."""
    given = profile.sim.sensor.response.get(channel.name)
    if given is not None:
        return np.array(given, dtype=np.float64)
    return np.array([np.interp(channel.wavelength_nm, TYPICAL_QE[:, 0], TYPICAL_QE[:, k]) for k in (1, 2, 3)])


def sensor_pixels_per_slm_pixel(profile: Profile) -> float:
    """Linear scale of the camera geometry: target-plane pixels (SLM pitch) -> sensor pixels."""
    slm = profile.require("slm").slm
    assert slm is not None
    return profile.sim.imaging.magnification * slm.pitch_um / profile.sim.sensor.pixel_um


def camera_homography(profile: Profile) -> np.ndarray:
    """3x3 homography from target-plane pixel coordinates (x = column, y = row of the SLM grid, pixel centres
    at integers) to coordinates in the sensor's active area (the visible mosaic `decode_raw` returns).

    The grid's centre lands `offset_px` [rows, cols] from the active area's centre; the image is scaled by
    magnification x SLM pitch / sensor pitch and turned by rotation_deg (clockwise as displayed).
    """
    slm, imaging, sensor = profile.require("slm").slm, profile.sim.imaging, profile.sim.sensor
    assert slm is not None
    scale, angle = sensor_pixels_per_slm_pixel(profile), math.radians(imaging.rotation_deg)
    linear = scale * np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    rows, cols = (size - margin for size, margin in zip(sensor.shape, sensor.margin))
    grid_centre = np.array([(slm.width - 1) / 2, (slm.height - 1) / 2])
    image_centre = np.array([(cols - 1) / 2 + imaging.offset_px[1], (rows - 1) / 2 + imaging.offset_px[0]])
    homography = np.eye(3)
    homography[:2, :2] = linear
    homography[:2, 2] = image_centre - linear @ grid_centre
    return homography


def dn_per_electron(sensor: SimSensorConfig, iso: int) -> float:
    """Gain: full_well_e reaches the white level at base_iso; the gain is proportional to the ISO."""
    return (sensor.white_level - sensor.black_level) / sensor.full_well_e * iso / sensor.base_iso


def emitting_channels(profile: Profile) -> dict[str, float]:
    """Power (W) of each laser channel that emits now, as its simulated laser unit holds it (sim:// ports).

    A unit's state is saved under its sim:// device name, by the channel number the driver addresses: the
    channel's index on a template unit or a shared port (OBIS box), 1 on a single head (Cobolt, OBIS).
    """
    if profile.laser is None:
        return {}
    laser = profile.laser
    sharing = Counter(laser.port_of(channel) for channel in laser.channels)
    powers = {}
    for channel in laser.channels:
        port = laser.port_of(channel)
        try:
            device, _ = parse_url(port)
        except SerialException:
            raise DeviceError(f"simulated camera: laser channel {channel.name!r} is on {port}, not a sim:// port; "
                              "the simulated bench sees only simulated lasers") from None
        number = channel.index if laser.driver == "template" or sharing[port] > 1 else 1
        state = load_state(device).get("channels", {}).get(str(number), {})
        if state.get("emission") and state.get("setpoint_w", 0.0) > 0:
            powers[channel.name] = float(state["setpoint_w"])
    return powers


@functools.lru_cache(maxsize=3)
def _propagator(setup: OpticalSetup) -> Propagator:
    """The target propagator of the first setup equal to `setup`, so its transfer function is computed once."""
    return setup.target_propagator()


@functools.lru_cache(maxsize=3)
def _illumination(shape: tuple[int, int], pitch_m: float | tuple[float, float], waist_mm: float,
                  offset_mm: tuple[float, ...], tilt_mrad: tuple[float, ...], wavelength_m: float,
                  waves: tuple[tuple[str, float], ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """The light one channel brings to the panel, computed once (its Zernike terms take half a second at full
    size): the amplitude on each pixel (float32, the square root of the beam's power fraction there: uniform, or a
    Gaussian) and e^(i (tilt + wavefront error)) (complex64). Callers must not modify them."""
    if waist_mm:
        power = gaussian_beam_power(shape, pitch_m, waist_mm * 1e-3, [v * 1e-3 for v in offset_mm])
    else:
        power = torch.full(shape, 1.0 / (shape[0] * shape[1]), dtype=torch.float64)
    amplitude = power.sqrt().to(torch.float32)
    wavefront = (tilt_phase(shape, pitch_m, [v * 1e-3 for v in tilt_mrad], wavelength_m)
                 + wavefront_phase(shape, pitch_m, dict(waves)))
    return amplitude, torch.polar(torch.ones_like(amplitude), wavefront.to(torch.float32))


def _target_irradiance(profile: Profile, channel: LaserChannel, gray: np.ndarray) -> torch.Tensor:
    """Fraction of the beam's power on each target-plane pixel, (H, W) float64, for one channel.

    The driven phase (true response, blurred by crosstalk) modulates all but the pixel gaps' light; the beam's
    tilt and the channel's wavefront error act on all of it; stray light spreads a fraction evenly."""
    slm, sim = profile.slm, profile.sim
    assert slm is not None
    driven = gray_to_phase(gray, true_lut(channel.wavelength_m, slm.bit_depth, sim.slm))
    phase = crosstalk_blur(torch.from_numpy(driven), sim.slm.crosstalk_px)
    gap = sim.slm.zero_order
    beam = sim.beam
    amplitude, wavefront = _illumination(slm.shape, slm.pitch_m, beam.waist_mm, tuple(beam.offset_mm),
                                         tuple(beam.tilt_mrad), channel.wavelength_m,
                                         tuple(sim.aberration.get(channel.name, {}).items()))
    field = (torch.polar(amplitude * (1 - gap), phase) + amplitude * gap) * wavefront
    with torch.inference_mode():
        out = _propagator(OpticalSetup.of(profile.geometry(channel.name)))(field)
    irradiance = out.abs().square().to(torch.float64)
    stray = sim.imaging.stray_light
    return (1 - stray) * irradiance + stray * irradiance.mean() if stray else irradiance


def _lit_box(profile: Profile, homography: np.ndarray) -> tuple[int, int, int, int] | None:
    """(top, bottom, left, right) in active-area coordinates of the pixels the SLM grid's image can reach."""
    slm, sensor = profile.slm, profile.sim.sensor
    assert slm is not None
    corners = np.array([[-0.5, -0.5, 1], [slm.width - 0.5, -0.5, 1], [-0.5, slm.height - 0.5, 1],
                        [slm.width - 0.5, slm.height - 0.5, 1]]) @ homography.T
    rows, cols = (size - margin for size, margin in zip(sensor.shape, sensor.margin))
    top, left = (max(0, math.floor(v.min()) - 1) for v in (corners[:, 1], corners[:, 0]))
    bottom, right = min(rows, math.ceil(corners[:, 1].max()) + 2), min(cols, math.ceil(corners[:, 0].max()) + 2)
    return (top, bottom, left, right) if top < bottom and left < right else None


def _mean_electrons(profile: Profile, gray: np.ndarray | None, powers_w: Mapping[str, float],
                    exposure_s: float) -> tuple[tuple[int, int, int, int], np.ndarray] | None:
    """The lit box of the active area and the mean photo-electrons in each of its pixels (float64), or None."""
    slm = profile.require("slm", "optics").slm
    assert slm is not None
    if gray is None:
        gray = np.zeros(slm.shape, dtype=np.uint16)  # a panel that has shown nothing shows gray 0
    if gray.shape != slm.shape:
        raise DeviceError(f"simulated SLM shows a {gray.shape[0]} x {gray.shape[1]} frame, the profile's SLM is "
                          f"{slm.height} x {slm.width}: show a frame with this profile first")
    homography = camera_homography(profile)
    box = _lit_box(profile, homography)
    if box is None:
        return None
    electrons = np.zeros((*slm.shape, 3), dtype=np.float32)  # per target pixel, as seen by R, G and B pixels
    for name, watts in powers_w.items():
        channel = profile.channel(name)
        photons = watts * exposure_s * channel.wavelength_m / (PLANCK_J_S * LIGHT_M_S) * profile.sim.beam.efficiency
        irradiance = _target_irradiance(profile, channel, gray).numpy() * photons
        electrons += (irradiance[..., None] * spectral_response(profile, channel)).astype(np.float32)
    top, bottom, left, right = box
    shift = np.array([[1.0, 0, -left], [0, 1.0, -top], [0, 0, 1.0]])
    warped = cv2.warpAffine(electrons, (shift @ homography)[:2], (right - left, bottom - top),
                            flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    warped /= sensor_pixels_per_slm_pixel(profile) ** 2  # energy per target pixel spread over the image's area
    colours = np.array(CFA_LAYOUTS[profile.sim.sensor.cfa]).reshape(2, 2)
    mean = np.empty(warped.shape[:2], dtype=np.float64)
    for dy in (0, 1):
        for dx in (0, 1):  # the active area starts on the CFA's top-left cell (its margins are even)
            r0, c0 = (dy - top) % 2, (dx - left) % 2
            mean[r0::2, c0::2] = warped[r0::2, c0::2, colours[dy, dx]]
    return box, mean


def render_mosaic(profile: Profile, gray: np.ndarray | None, powers_w: Mapping[str, float], *,
                  exposure_s: float, iso: int, frame: int) -> np.ndarray:
    """The raw frame (uint16, margins included) the sensor records of `gray` on the SLM lit by `powers_w`
    (channel name -> W, the channels that emit), drawn from the random stream (sim.seed, frame)."""
    sensor = profile.sim.sensor
    rng = np.random.default_rng([profile.sim.seed, frame])
    gain = dn_per_electron(sensor, iso)
    raw = rng.standard_normal(sensor.shape, dtype=np.float32)
    raw *= np.float32(sensor.read_noise_e * gain)
    raw += np.float32(sensor.black_level)
    lit = _mean_electrons(profile, gray, powers_w, exposure_s) if powers_w else None
    if lit is not None:
        (top, bottom, left, right), mean = lit
        rows, cols = sensor.margin[0] + top, sensor.margin[1] + left
        region = raw[rows:rows + bottom - top, cols:cols + right - left]
        region += (rng.poisson(mean) * gain).astype(np.float32)
    np.rint(raw, out=raw)
    return np.clip(raw, 0, sensor.white_level).astype(np.uint16)


def render_capture(profile: Profile, exposure_s: float | None = None, iso: int | None = None) -> RawFrame:
    """Release the simulated shutter: the DNG of what the sensor records now (the simulated SLM's frame, lit by
    the simulated lasers that emit). None for exposure_s / iso: the simulated body's own settings ([sim.sensor])."""
    sim = profile.sim
    sensor = sim.sensor
    exposure_s = sensor.exposure_s if exposure_s is None else exposure_s
    iso = sensor.iso if iso is None else iso
    state = load_state(CAMERA_STATE)
    number = int(state.get("frame", 0)) + 1
    save_state(CAMERA_STATE, {**state, "frame": number})
    powers = emitting_channels(profile)
    gray, shown = read_displayed()
    mosaic = render_mosaic(profile, gray, powers, exposure_s=exposure_s, iso=iso, frame=number)
    now = datetime.now()
    data = dng_bytes(mosaic, cfa=sensor.cfa, black_level=sensor.black_level, white_level=sensor.white_level,
                     camera_model=sensor.model, active_area=sensor.active_area, exposure_s=exposure_s, iso=iso,
                     datetime=now.strftime("%Y:%m:%d %H:%M:%S"))
    metadata = {"exposure_s": exposure_s, "iso": iso, "lasers_on_w": powers, "slm_frame": shown.get("frame"),
                "seed": sim.seed, "frame": number, "captured_at": now.isoformat(timespec="milliseconds"),
                "camera": sensor.model}
    return RawFrame(data, "dng", f"IMG_{number:04d}.DNG", metadata)
