"""The simulated camera focuses where the simulated focus mechanism puts it: captures blur and sharpen as propagation
says, with the depth of field of the bench's own aperture (the Fourier iris), checked against the analytic through-
focus intensity of a coherent focus and against geometric optics far from focus."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import torch

from benchctl.devices.sim import physics
from benchctl.devices.sim.focus_mechanics import FOCUS_STATE, Mechanism
from benchctl.devices.sim.state import save_state
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile

N, PITCH, WAVELENGTH, Z0_MM, IRIS = 256, 8e-6, 520e-9, 50.0, 0.5
FC = IRIS / (2 * PITCH)  # the iris's radius in spatial frequency (1/m)
NA = WAVELENGTH * FC
MM_PER_STEP, START = 0.001, 30000


@pytest.fixture
def focus_bench(make_bench_profile: Any) -> Profile:
    """A 256 x 256, 8 um SLM at 50 mm with an iris of 0.5 x Nyquist (NA 0.0163), its camera on a simulated stage
    whose focus plane moves 1 um per step, at 50 mm at power-on."""
    return make_bench_profile(
        optics={"distance_mm": Z0_MM, "roi": [N, N], "iris_fraction": IRIS},
        slm={"width": N, "height": N, "pitch_um": PITCH * 1e6},
        focus={"driver": "zaber", "port": "sim://focus-stage?dialect=zaber"},
        sim={"focus": {"mm_per_step": MM_PER_STEP, "range_steps": 2 * START, "start_steps": START},
             "slm": {"zero_order": 0.0, "two_pi_nm": 520.0, "gamma": 1.0}})


def set_focus(dz_mm: float) -> None:
    """Put the mechanism where the camera focuses dz_mm beyond the target plane."""
    save_state(FOCUS_STATE, {"true_steps": START + dz_mm / MM_PER_STEP, "play": 0.0, "moves": 0})


def focused_point() -> torch.Tensor:
    """The SLM field whose light comes to a point Z0 downstream through the iris: the iris's disc of spatial
    frequencies, each carrying the conjugate of its exact angular-spectrum phase over Z0 (float64)."""
    f = np.fft.fftfreq(N, PITCH)
    f2 = f[:, None] ** 2 + f[None, :] ** 2
    disc = f2 < FC**2
    phase = 2 * math.pi * Z0_MM * 1e-3 * (np.sqrt(1 / WAVELENGTH**2 - f2) - 1 / WAVELENGTH)
    field = np.fft.ifft2(disc * np.exp(-1j * phase))
    return torch.from_numpy(np.fft.fftshift(field)).to(torch.complex64)  # the point at the grid's centre


def camera_intensity(profile: Profile) -> np.ndarray:
    geometry = physics.camera_geometry(profile, "green")
    with torch.inference_mode():
        out = OpticalSetup.of(geometry).target_propagator()(focused_point())
    return out.abs().square().double().numpy()


def test_an_untouched_mechanism_focuses_on_the_target_plane(focus_bench: Profile) -> None:
    assert physics.camera_focus_m(focus_bench) == pytest.approx(Z0_MM * 1e-3)
    assert physics.camera_geometry(focus_bench, "green") == focus_bench.geometry("green")
    set_focus(2.0)
    assert physics.camera_geometry(focus_bench, "green").distance_m == pytest.approx((Z0_MM + 2.0) * 1e-3)


def test_on_axis_intensity_through_focus_is_the_coherent_sinc_squared(focus_bench: Profile) -> None:
    """|U(dz)|^2 / |U(0)|^2 = sinc^2(lambda dz fc^2 / 2) for a uniform disc of frequencies (paraxial; NA 0.016):
    its first zero, the depth of field, at 2 lambda / NA^2 = 3.94 mm."""
    set_focus(0.0)
    peak = camera_intensity(focus_bench)[N // 2, N // 2]
    for dz in (-2.5, -1.0, 1.0, 2.0, 3.0, 3.94, 6.0):
        set_focus(dz)
        measured = camera_intensity(focus_bench)[N // 2, N // 2] / peak
        expected = np.sinc(WAVELENGTH * dz * 1e-3 * FC**2 / 2) ** 2
        assert measured == pytest.approx(expected, abs=0.02), dz


def test_far_from_focus_the_blur_is_the_geometric_cone(focus_bench: Profile) -> None:
    """20 mm (5 depths of field) out of focus the light fills the cone's disc of radius NA dz uniformly: a quarter of
    it within half that radius, nearly all within it."""
    dz = 20.0
    set_focus(dz)
    intensity = camera_intensity(focus_bench)
    radius_px = NA * dz * 1e-3 / PITCH  # 40.6 px
    y, x = np.indices(intensity.shape) - N // 2
    r = np.hypot(y, x)
    total = intensity.sum()
    for fraction in (0.3, 0.5, 0.7):  # a uniform disc holds fraction^2 within fraction x its radius
        assert intensity[r <= fraction * radius_px].sum() / total == pytest.approx(fraction**2, abs=0.03), fraction
    assert intensity[r <= 1.1 * radius_px].sum() / total > 0.93  # the edge is Fresnel-blurred by sqrt(lambda dz)


def test_captures_blur_and_sharpen_with_the_stage(focus_bench: Profile) -> None:
    """Through the whole simulated capture (SLM phase through the panel's response, the propagation to the camera's
    plane, the sensor): a Fresnel lens on the SLM focusing at Z0 is brightest at the centre with the stage there."""
    y, x = (np.indices((N, N)) - (N - 1) / 2) * PITCH
    lens = -math.pi * (x**2 + y**2) / (WAVELENGTH * Z0_MM * 1e-3)
    gray = np.round(np.mod(lens, 2 * math.pi) / (2 * math.pi) * 256).astype(np.uint16) % 256
    green = focus_bench.channel("green")
    peaks = {}
    for dz in (-3.0, -1.0, 0.0, 1.0, 3.0):
        set_focus(dz)
        peaks[dz] = float(physics._target_irradiance(focus_bench, green, gray).max())
    assert max(peaks, key=peaks.__getitem__) == 0.0
    assert peaks[-3.0] < 0.3 * peaks[0.0] and peaks[3.0] < 0.3 * peaks[0.0]
    assert Mechanism(focus_bench.sim.focus, Z0_MM).plane_m == pytest.approx(0.053)
