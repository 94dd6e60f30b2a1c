"""The simulated bench's camera physics: what a real sensor would record from the simulated SLM and lasers.

Per capture, for every laser channel that emits (and only those): the gray frame the simulated SLM shows
becomes a phase through the simulator's own response ([sim.slm], deliberately not the profile's lookup table),
lit by the laser's power (uniform, or a Gaussian beam), with a little unmodulated light from the pixel gaps;
it is propagated to the target plane by the same Propagator the holograms are computed with, at the profile's
geometry (`OpticalSetup.of(profile.geometry(...)).target_propagator()`, Fourier iris included) - or, where a simulated
focus mechanism moved the camera's focus plane, to that plane (`camera_geometry`) - and becomes
photons (P t lambda / (h c) times the optical efficiency). The three colour planes of electrons (each channel's
photons times its [R, G, B] quantum efficiency) are carried onto the sensor by the camera homography
(magnification, rotation, offset; energy conserving) into only the box of sensor pixels the grid's image
covers. The sensor adds shot noise (Poisson, electrons), read noise (Gaussian, electrons), the ISO gain,
the black level, clipping at the white level and integer quantisation; masked margins and unlit pixels get
black level plus read noise only. docs/simulated_bench.md describes the model and its parameters.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections import Counter
from collections.abc import Callable, Mapping
from datetime import datetime
from typing import Any

import cv2
import numpy as np
import torch
from serial.serialutil import SerialException

from benchctl.devices.camera.base import RawFrame, Window
from benchctl.devices.errors import DeviceError
from benchctl.devices.sim.focus_mechanics import Mechanism
from benchctl.devices.sim.protocol_sim import parse_url
from benchctl.devices.sim.slm import read_displayed, true_lut
from benchctl.devices.sim.state import CAMERA_STATE, load_state, save_state
from benchctl.dng import CFA_LAYOUTS, dng_bytes
from benchctl.optics import Propagator, PrunedPropagator, gray_to_phase, linear_to_srgb
from benchctl.optics.aberration import crosstalk_blur, gaussian_beam_power, tilt_phase, wavefront_phase
from benchctl.optics.geometry import Geometry
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import LaserChannel, Profile, SimSensorConfig, SimSLMConfig

PLANCK_J_S = 6.62607015e-34
LIGHT_M_S = 299792458.0

POISSON_BELOW = 50.0  # electrons in a live-view bin below which its shot noise is drawn as Poisson
SATURATION_SAMPLES = 2_000_000  # sensor pixels a live-view frame evaluates, at most, to find saturated bins
COARSE = 2  # a progressive live view's first frame after a change: the light on a grid this many times coarser

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


def camera_focus_m(profile: Profile) -> float | None:
    """The depth (from the SLM) the simulated camera focuses at, where the profile's [focus] is a simulated mechanism
    (a Zaber stage on a sim:// port, or the simulated EOS body's lens): the mechanism's true plane
    (benchctl.devices.sim.focus_mechanics). None without one: the camera sees the target plane."""
    focus, camera = profile.focus, profile.camera
    if focus is None:
        return None
    simulated = ((focus.driver == "zaber" and (focus.port or "").startswith("sim://"))
                 or (focus.driver == "eos" and camera is not None and camera.transport == "sim"))
    if not simulated:
        return None
    distance = profile.optics.distance_mm if profile.optics else None
    return Mechanism(profile.sim.focus, distance).plane_m


def camera_geometry(profile: Profile, channel: str) -> Geometry:
    """`channel`'s geometry as the camera sees it: propagated to the plane the camera focuses at (the target plane
    unless a simulated focus moved it). The camera images that plane coherently through the same band limit and iris,
    so out-of-focus light blurs exactly as propagation says and the depth of field is the bench's own aperture's."""
    geometry = profile.geometry(channel)
    plane = camera_focus_m(profile)
    if plane is None or plane == geometry.distance_m:
        return geometry
    if plane <= 0:
        raise DeviceError(f"simulated camera: its focus plane is {plane * 1e3:g} mm from the SLM, not in front of it "
                          f"(check [sim.focus])")
    return dataclasses.replace(geometry, distance_m=plane)


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


def _beam(profile: Profile, channel: LaserChannel) -> tuple[Any, ...]:
    """The arguments of `_illumination` for `channel`, as the profile's [sim.beam] and [sim.aberration] say."""
    slm, sim = profile.slm, profile.sim
    assert slm is not None
    beam = sim.beam
    return (slm.shape, slm.pitch_m, beam.waist_mm, tuple(beam.offset_mm), tuple(beam.tilt_mrad),
            channel.wavelength_m, tuple(sim.aberration.get(channel.name, {}).items()))


def _panel_field(profile: Profile, channel: LaserChannel, gray: np.ndarray) -> torch.Tensor:
    """The field leaving the panel (H, W) complex64: the driven phase (true response, blurred by crosstalk)
    modulates all but the pixel gaps' light; the beam's tilt and the channel's wavefront error act on all of it."""
    slm, sim = profile.slm, profile.sim
    assert slm is not None
    driven = gray_to_phase(gray, true_lut(channel.wavelength_m, slm.bit_depth, sim.slm))
    phase = crosstalk_blur(torch.from_numpy(driven), sim.slm.crosstalk_px)
    gap = sim.slm.zero_order
    amplitude, wavefront = _illumination(*_beam(profile, channel))
    return (torch.polar(amplitude * (1 - gap), phase) + amplitude * gap) * wavefront


def _with_stray_light(profile: Profile, irradiance: torch.Tensor) -> torch.Tensor:
    """Stray light spreads a fraction of the target plane's light evenly over it."""
    stray = profile.sim.imaging.stray_light
    return (1 - stray) * irradiance + stray * irradiance.mean() if stray else irradiance


def _target_irradiance(profile: Profile, channel: LaserChannel, gray: np.ndarray) -> torch.Tensor:
    """Fraction of the beam's power on each target-plane pixel, (H, W) float64, for one channel: the panel's
    field (`_panel_field`) propagated to the target plane, stray light added."""
    field = _panel_field(profile, channel, gray)
    with torch.inference_mode():
        out = _propagator(OpticalSetup.of(camera_geometry(profile, channel.name)))(field)
    return _with_stray_light(profile, out.abs().square().to(torch.float64))


@functools.lru_cache(maxsize=8)
def _modulation(wavelength_m: float, bit_depth: int, response: SimSLMConfig) -> np.ndarray:
    """Per gray level g the field the simulated panel passes of unit light, (1 - f) e^(i phase(g)) + f with f its
    unmodulated fraction (complex64): `_panel_field` by table lookup where no crosstalk blurs the phase."""
    table = (1 - response.zero_order) * np.exp(1j * true_lut(wavelength_m, bit_depth, response).phases)
    return (table + response.zero_order).astype(np.complex64)


@functools.lru_cache(maxsize=3)
def _beam_field(*beam: Any) -> torch.Tensor:
    """`_illumination(*beam)`'s amplitude times its tilt and wavefront error, (H, W) complex64, computed once."""
    amplitude, wavefront = _illumination(*beam)
    return amplitude * wavefront


@functools.lru_cache(maxsize=3)
def _pruned_propagator(setup: OpticalSetup) -> PrunedPropagator:
    return PrunedPropagator(_propagator(setup))


def _live_irradiance(profile: Profile, channel: LaserChannel, gray: np.ndarray, coarse: int = 1) -> torch.Tensor:
    """`_target_irradiance` (float32) as the live view computes it, faster: the panel's field by table lookup
    where no crosstalk blurs the phase, propagated by `PrunedPropagator`. `coarse` > 1 (dividing the grid): the
    field averaged over coarse x coarse pixels and propagated on that coarser grid (the same bench: pitch times
    `coarse`, the iris at the same spatial frequency), each coarse pixel's light repeated over the pixels it
    covers; about coarse^2 times faster, and what the iris passes below the coarse grid's Nyquist frequency is the
    same light (a progressive preview's first frame)."""
    slm, response = profile.slm, profile.sim.slm
    assert slm is not None
    if response.crosstalk_px:
        field = _panel_field(profile, channel, gray)
    else:
        field = torch.from_numpy(_modulation(channel.wavelength_m, slm.bit_depth, response)[gray])
        field *= _beam_field(*_beam(profile, channel))
    geometry = camera_geometry(profile, channel.name)
    rows, cols = geometry.shape
    if coarse > 1 and rows % coarse == 0 and cols % coarse == 0:
        rows_summed = field[0::coarse].clone()  # strided sums, rows then columns: a quarter of torch.mean's time
        for offset in range(1, coarse):
            rows_summed += field[offset::coarse]
        field = rows_summed[:, 0::coarse].clone()
        for offset in range(1, coarse):
            field += rows_summed[:, offset::coarse]
        field /= coarse**2
        (roi_rows, roi_cols), (pitch_y, pitch_x) = geometry.roi, geometry.pitch_m
        geometry = dataclasses.replace(
            geometry, shape=(rows // coarse, cols // coarse), roi=(roi_rows // coarse, roi_cols // coarse),
            pitch_m=(pitch_y * coarse, pitch_x * coarse),
            aperture=None if geometry.aperture is None else min(1.0, geometry.aperture * coarse))
    else:
        coarse = 1
    setup = OpticalSetup.of(geometry)
    with torch.inference_mode():
        out = (_coarse_propagator(setup, coarse) if coarse > 1 else _pruned_propagator(setup))(field)
    light = _with_stray_light(profile, out.real.square() + out.imag.square())
    return light.repeat_interleave(coarse, 0).repeat_interleave(coarse, 1) if coarse > 1 else light


@functools.lru_cache(maxsize=3)
def _coarse_propagator(setup: OpticalSetup, coarse: int) -> PrunedPropagator:
    """`_pruned_propagator(setup)` for a field averaged over coarse x coarse pixels, its transfer function divided
    by that average's response (sin(pi f) / (coarse sin(pi f / coarse)) per axis at f cycles per coarse pixel):
    a grating keeps its light (a 6-pixel one lost 28 % to the average)."""
    pruned = PrunedPropagator(_propagator(setup))
    (ph, pw), response = pruned.padded_shape, []
    for n, low, high in ((ph, pruned.low_y, pruned.high_y), (pw, pruned.low_x, pruned.high_x)):
        f = torch.fft.fftfreq(n, dtype=torch.float64)
        f = torch.cat([f[:low], f[n - high:]])
        response.append(torch.where(f == 0, 1.0, torch.sin(math.pi * f) / (coarse * torch.sin(math.pi * f / coarse))))
    pruned.kernel = (pruned.kernel / (response[0][:, None] * response[1][None, :])).to(pruned.kernel.dtype)
    return pruned


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


def _electron_planes(profile: Profile, gray: np.ndarray | None, powers_w: Mapping[str, float], exposure_s: float,
                     irradiance: Callable[[Profile, LaserChannel, np.ndarray], torch.Tensor] = _target_irradiance,
                     ) -> np.ndarray:
    """Mean photo-electrons per target-plane pixel as the sensor's R, G and B pixels collect them: (H, W, 3)
    float32, the emitting channels' photons times their quantum efficiencies, before the camera geometry.
    `irradiance`: how each channel's light is computed (the live view's is faster)."""
    slm = profile.require("slm", "optics").slm
    assert slm is not None
    if gray is None:
        gray = np.zeros(slm.shape, dtype=np.uint16)  # a panel that has shown nothing shows gray 0
    if gray.shape != slm.shape:
        raise DeviceError(f"simulated SLM shows a {gray.shape[0]} x {gray.shape[1]} frame, the profile's SLM is "
                          f"{slm.height} x {slm.width}: show a frame with this profile first")
    electrons = np.zeros((*slm.shape, 3), dtype=np.float32)  # per target pixel, as seen by R, G and B pixels
    for name, watts in powers_w.items():
        channel = profile.channel(name)
        photons = watts * exposure_s * channel.wavelength_m / (PLANCK_J_S * LIGHT_M_S) * profile.sim.beam.efficiency
        light = irradiance(profile, channel, gray).numpy() * photons
        electrons += (light[..., None] * spectral_response(profile, channel).astype(light.dtype)).astype(
            np.float32, copy=False)
    return electrons


def _sensor_electrons(profile: Profile, planes: np.ndarray, homography: np.ndarray, shape: tuple[int, int],
                      origin: tuple[int, int] | None) -> np.ndarray:
    """Mean electrons per sensor pixel on a grid of `shape` pixels that `homography` maps target-plane pixels to:
    the planes resampled (bilinear) and divided by the sensor pixels per target pixel squared (energy conserved).
    With `origin` (the grid's first pixel in active-area coordinates), each pixel keeps the colour of its CFA
    position: (rows, cols) float64; without, all three colours: (rows, cols, 3) float32."""
    warped: np.ndarray = cv2.warpAffine(planes, homography[:2], (shape[1], shape[0]), flags=cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    warped /= sensor_pixels_per_slm_pixel(profile) ** 2  # energy per target pixel spread over the image's area
    if origin is None:
        return warped
    colours = np.array(CFA_LAYOUTS[profile.sim.sensor.cfa]).reshape(2, 2)
    top, left = origin
    mean = np.empty(warped.shape[:2], dtype=np.float64)
    for dy in (0, 1):
        for dx in (0, 1):  # the active area starts on the CFA's top-left cell (its margins are even)
            r0, c0 = (dy - top) % 2, (dx - left) % 2
            mean[r0::2, c0::2] = warped[r0::2, c0::2, colours[dy, dx]]
    return mean


def _mean_electrons(profile: Profile, gray: np.ndarray | None, powers_w: Mapping[str, float],
                    exposure_s: float) -> tuple[tuple[int, int, int, int], np.ndarray] | None:
    """The lit box of the active area and the mean photo-electrons in each of its pixels (float64), or None."""
    homography = camera_homography(profile)
    box = _lit_box(profile, homography)
    if box is None:
        return None
    planes = _electron_planes(profile, gray, powers_w, exposure_s)
    top, bottom, left, right = box
    shift = np.array([[1.0, 0, -left], [0, 1.0, -top], [0, 0, 1.0]])
    return box, _sensor_electrons(profile, planes, shift @ homography, (bottom - top, right - left), (top, left))


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


def _binned_electrons(rng: np.random.Generator, expected: np.ndarray, read_variance: float) -> np.ndarray:
    """Electrons a bin reads: its photo-electrons (Poisson, mean `expected`) plus its pixels' read noise (normal,
    `read_variance`), float32. Where a bin expects POISSON_BELOW electrons or more the two are drawn as one normal of
    their summed variance (Poisson's normal approximation, far finer than a preview shows; a third of the time)."""
    few = expected < POISSON_BELOW
    if few.all():
        counts = rng.poisson(expected).astype(np.float32)
    else:
        counts = rng.standard_normal(expected.shape, dtype=np.float32)
        counts *= np.sqrt(expected + np.float32(read_variance))
        counts += expected
        counts[few] = rng.poisson(expected[few])
    counts[few] += rng.standard_normal(int(few.sum()), dtype=np.float32) * np.float32(math.sqrt(read_variance))
    return counts


class LiveView:
    """The simulated sensor's live view: what the camera shows while nobody captures, from the same physics as a
    capture (`render_capture`) at the size a screen needs.

    A live-view frame is a binned readout of a window of the active area: each pixel is the mean of `bin` x `bin`
    sensor pixels of one CFA position (the Bayer layout is kept), with the shot and read noise of that mean, the
    gain, black level, clipping and quantisation of a capture. Only the light is expensive (a propagation per
    emitting channel, `_live_irradiance`: the capture's light, computed faster): it is computed once per SLM frame,
    laser state and exposure and reused until one changes, so frames in between cost the resampling and the noise.
    `progressive` (the default): after a change the first frame shows the light computed on a grid COARSE times
    coarser (metadata `coarse`: true), so the change reaches the screen sooner, and the next frame refines it.
    Where one frame pixel covers two or more target-plane pixels, those are averaged first (area sampling, not point
    sampling: a hologram's fine detail does not alias). A bin's mean can stay below the white level while some of
    its pixels reach it: the metadata's `saturated_bins` marks every bin that holds a sensor pixel whose mean signal
    reaches the white level (noise aside).
    """

    def __init__(self, profile: Profile, progressive: bool = True) -> None:
        self.profile = profile
        self.progressive = progressive
        self._key: tuple | None = None
        self._coarse = False  # the planes are a progressive first frame's: the next frame refines them
        self._planes: np.ndarray | None = None
        self._reduced: dict[int, np.ndarray] = {}
        self._saturated: dict[tuple, np.ndarray | None] = {}
        self._frames = 0

    @property
    def active_shape(self) -> tuple[int, int]:
        """(rows, cols) of the sensor's active area."""
        sensor = self.profile.sim.sensor
        return sensor.shape[0] - sensor.margin[0], sensor.shape[1] - sensor.margin[1]

    def window(self, window: Window | None) -> Window:
        """`window` inside the active area, its corner on a CFA cell (even row and column); None: all of it."""
        rows_a, cols_a = self.active_shape
        if window is None:
            return 0, 0, rows_a, cols_a
        top, left, rows, cols = (int(v) for v in window)
        top, left = min(max(0, top), rows_a - 2) & ~1, min(max(0, left), cols_a - 2) & ~1
        return top, left, max(2, min(rows, rows_a - top)), max(2, min(cols, cols_a - left))

    def _light(self, exposure_s: float) -> tuple[np.ndarray, dict[str, Any]]:
        """The electron planes of what the bench shows now (recomputed only when the SLM frame, the lasers or the
        exposure changed) and what they show: SLM frame, lasers, seconds spent on the light (0: reused)."""
        from benchctl.devices.sim.slm import STATE_NAME

        powers = emitting_channels(self.profile)
        shown = load_state(STATE_NAME).get("frame")
        key = (shown, tuple(sorted(powers.items())), exposure_s, camera_focus_m(self.profile))
        start = time.perf_counter()
        if key != self._key or self._planes is None or self._coarse:
            gray, state = read_displayed() if shown is not None else (None, {})
            key = (state.get("frame"), *key[1:])  # the frame read, should a newer one have come
            # progressive: a change is shown at once from the coarse light, and the next frame refines it
            coarse = self.progressive and self._planes is not None and key != self._key
            irradiance = functools.partial(_live_irradiance, coarse=COARSE if coarse else 1)
            self._planes = _electron_planes(self.profile, gray, powers, exposure_s, irradiance)
            self._reduced, self._saturated = {}, {}
            self._key, self._coarse = key, coarse
        return self._planes, {"slm_frame": key[0], "lasers_on_w": dict(key[1]), "coarse": self._coarse,
                              "light_s": round(time.perf_counter() - start, 6)}

    def _planes_at(self, step: float) -> tuple[np.ndarray, np.ndarray]:
        """The light planes averaged over k x k target pixels (k = the whole target pixels one frame pixel spans,
        at least 1) and the map from their pixel coordinates to the full grid's."""
        assert self._planes is not None
        k = max(1, int(step))
        if k == 1:
            return self._planes, np.eye(3)
        if k not in self._reduced:
            rows, cols = (n // k for n in self._planes.shape[:2])
            self._reduced[k] = cv2.resize(self._planes[:rows * k, :cols * k], (cols, rows),
                                          interpolation=cv2.INTER_AREA)
        return self._reduced[k], np.array([[k, 0, (k - 1) / 2], [0, k, (k - 1) / 2], [0, 0, 1.0]])

    def render(self, width: int, window: Window | None = None, *, exposure_s: float | None = None,
               iso: int | None = None, cfa: bool = True) -> tuple[np.ndarray, dict[str, Any]]:
        """One frame of `window` (None: the whole active area) about `width` pixels wide (never finer than the
        sensor): a uint16 mosaic with the sensor's CFA layout (`cfa`), or (rows, cols, 3) uint16 with every colour
        at every pixel (a body's processed live view), in raw counts with the black level; and its metadata."""
        sensor = self.profile.sim.sensor
        exposure_s = sensor.exposure_s if exposure_s is None else exposure_s
        iso = sensor.iso if iso is None else iso
        top, left, rows, cols = self.window(window)
        binning = max(1.0, cols / max(1, int(width)))
        shape = (max(2, round(rows / binning)) & ~1, max(2, round(cols / binning)) & ~1)
        planes, metadata = self._light(exposure_s)
        reduced, to_full = self._planes_at(binning / sensor_pixels_per_slm_pixel(self.profile))
        to_frame = np.array([[1 / binning, 0, (0.5 - left) / binning - 0.5],
                             [0, 1 / binning, (0.5 - top) / binning - 0.5], [0, 0, 1.0]])
        homography = to_frame @ camera_homography(self.profile)
        mean = _sensor_electrons(self.profile, reduced, homography @ to_full, shape, (0, 0) if cfa else None)
        self._frames += 1
        rng = np.random.default_rng([self.profile.sim.seed, 1 << 32, self._frames])  # apart from captures' streams
        pixels = binning * binning  # sensor pixels averaged into one frame pixel
        gain = dn_per_electron(sensor, iso)
        counts = _binned_electrons(rng, (mean * pixels).astype(np.float32), sensor.read_noise_e**2 * pixels)
        counts *= np.float32(gain / pixels)
        counts += np.float32(sensor.black_level)
        np.rint(counts, out=counts)
        frame = np.clip(counts, 0, sensor.white_level).astype(np.uint16)
        metadata = {**metadata, "frame": self._frames, "window": [top, left, rows, cols], "bin": round(binning, 4),
                    "exposure_s": exposure_s, "iso": iso}
        saturated = self._saturated_bins((top, left, rows, cols), binning, shape, iso)
        if saturated is not None:
            metadata["saturated_bins"] = saturated
        return frame, metadata

    def _saturated_bins(self, window: Window, binning: float, shape: tuple[int, int],
                        iso: int) -> np.ndarray | None:
        """(rows, cols) bool: the frame pixels whose bin holds a sensor pixel whose mean signal reaches the white
        level (noise aside), that signal computed as a capture computes it; None where no bin does, or where a frame
        pixel is one sensor pixel (its own value says it). Computed once per light, ISO and frame geometry.

        A sensor pixel's signal is interpolated between its four nearest target-plane pixels, so it can reach the
        white level only next to a target pixel that would on its own ("hot"). Only the bins within reach of a hot
        pixel's image are candidates, and only their sensor pixels are evaluated (where that would be more than
        SATURATION_SAMPLES pixels, all candidates are marked: never too few)."""
        if binning <= 1:
            return None
        key = (iso, binning, *window, *shape)
        if key not in self._saturated:
            self._saturated[key] = self._find_saturated(window, binning, shape, iso)
        return self._saturated[key]

    def _find_saturated(self, window: Window, binning: float, shape: tuple[int, int], iso: int) -> np.ndarray | None:
        assert self._planes is not None
        sensor, spread = self.profile.sim.sensor, sensor_pixels_per_slm_pixel(self.profile)
        # a sensor pixel gets a target pixel's electrons spread over its image's area (`_sensor_electrons`)
        full = (sensor.white_level - sensor.black_level) / dn_per_electron(sensor, iso) * spread**2
        if self._planes.max() < full:
            return None
        hot_y, hot_x = np.nonzero(np.maximum.reduce([self._planes[..., c] for c in range(3)]) >= full)
        top, left = window[:2]
        homography = camera_homography(self.profile)
        images = homography[:2] @ np.stack([hot_x, hot_y, np.ones_like(hot_x)]).astype(np.float64)
        candidates = np.zeros(shape, np.uint8)
        rows = np.floor((images[1] - top + 0.5) / binning).astype(np.int64)
        cols = np.floor((images[0] - left + 0.5) / binning).astype(np.int64)
        inside = (rows >= -1) & (rows <= shape[0]) & (cols >= -1) & (cols <= shape[1])
        candidates[np.clip(rows[inside], 0, shape[0] - 1), np.clip(cols[inside], 0, shape[1] - 1)] = 1
        reach = math.ceil(1.5 * spread / binning) + 1  # bins a hot pixel's interpolation can touch
        candidates = cv2.dilate(candidates, np.ones((2 * reach + 1,) * 2, np.uint8)).astype(bool)
        bin_y, bin_x = np.nonzero(candidates)
        n = math.ceil(binning) + 1  # sensor pixels per bin and axis, at most
        if len(bin_y) * n * n > SATURATION_SAMPLES:
            return candidates
        offsets = np.arange(n)
        first_y, first_x = np.ceil(bin_y * binning - 0.5), np.ceil(bin_x * binning - 0.5)
        ys = first_y[:, None] + offsets  # (bins, n) sensor rows and columns of each bin, relative to the window
        xs = first_x[:, None] + offsets
        valid = ((ys < np.ceil((bin_y + 1) * binning - 0.5)[:, None])[:, :, None]
                 & (xs < np.ceil((bin_x + 1) * binning - 0.5)[:, None])[:, None, :])
        ys, xs = np.broadcast_arrays((ys + top)[:, :, None], (xs + left)[:, None, :])  # (bins, n, n) active area
        target = np.linalg.solve(homography, np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]))
        points = xs.size
        target = np.pad((target[:2] / target[2]).astype(np.float32), ((0, 0), (0, -points % 1024)))
        # laid out 1024 wide: OpenCV maps are at most 32767 rows long
        values = cv2.remap(self._planes, target[0].reshape(-1, 1024), target[1].reshape(-1, 1024), cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0).reshape(-1, 3)[:points]
        colours = np.array(CFA_LAYOUTS[sensor.cfa]).reshape(2, 2)[ys.astype(np.int64) % 2, xs.astype(np.int64) % 2]
        signal = np.take_along_axis(values, colours.reshape(-1, 1), axis=1).reshape(len(bin_y), n * n)
        saturated = np.zeros(shape, bool)
        saturated[bin_y, bin_x] = ((signal >= full) & valid.reshape(len(bin_y), -1)).any(axis=1)
        return saturated if saturated.any() else None

    def dng(self, width: int, window: Window | None = None, *, exposure_s: float | None = None,
            iso: int | None = None) -> tuple[bytes, dict[str, Any]]:
        """`render`'s mosaic as a DNG (what the simulated camera's preview delivers) and its metadata."""
        sensor = self.profile.sim.sensor
        mosaic, metadata = self.render(width, window, exposure_s=exposure_s, iso=iso)
        return dng_bytes(mosaic, cfa=sensor.cfa, black_level=sensor.black_level, white_level=sensor.white_level,
                         camera_model=sensor.model, exposure_s=metadata["exposure_s"], iso=metadata["iso"]), metadata

    def jpeg(self, width: int, *, exposure_s: float | None = None, iso: int | None = None) -> bytes:
        """The whole frame as a body's live view gives it: every colour at every pixel, black level removed, scaled
        to full scale, sRGB-encoded, JPEG (what the simulated EOS body sends for GetViewFinderData)."""
        sensor = self.profile.sim.sensor
        rgb, _ = self.render(width, exposure_s=exposure_s, iso=iso, cfa=False)
        signal = (rgb.astype(np.float32) - sensor.black_level) / (sensor.white_level - sensor.black_level)
        srgb = linear_to_srgb(torch.from_numpy(signal)).clamp(0, 1).mul(255).round().to(torch.uint8).numpy()
        ok, encoded = cv2.imencode(".jpg", cv2.cvtColor(srgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
        if not ok:
            raise DeviceError("simulated camera: live-view frame could not be encoded as JPEG")
        return encoded.tobytes()
