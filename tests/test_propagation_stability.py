"""Hard cases of propagation, one test each: zero and negative distances, a band limit that keeps almost
nothing, evanescent frequencies, odd and tiny grids, float32 at long distance, bad input, gradients at zero."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchctl.optics import Propagator, plan_propagation, propagate
from benchctl.optics.propagation import transfer_function


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.linalg.vector_norm(a.to(b.dtype) - b) / torch.linalg.vector_norm(b))


def _random_field(shape: tuple[int, ...], seed: int = 0, dtype: torch.dtype = torch.complex128) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    phase = (2 * torch.rand(shape, generator=generator, dtype=torch.float64) - 1) * math.pi
    amplitude = torch.rand(shape, generator=generator, dtype=torch.float64)
    return torch.polar(amplitude, phase).to(dtype)


def _energy(field: torch.Tensor) -> float:
    return float(field.abs().square().sum())


@pytest.mark.parametrize("padding", ["auto", "2x", "none", 3])
def test_zero_distance_is_identity(padding):
    field = _random_field((2, 17, 24))
    out = propagate(field, 0.0, 520e-9, 3.74e-6, padding=padding)
    assert out.dtype == field.dtype and torch.equal(out, field)
    assert out.data_ptr() != field.data_ptr()  # a new tensor: writing to it leaves the input alone
    assert plan_propagation((17, 24), 0.0, 520e-9, 3.74e-6, padding="auto").padded_shape == (17, 24)


def test_negative_distance_inverts_positive():
    shape, pitch, wavelength, z = (64, 80), 6.4e-6, 520e-9, 4e-3
    plus = Propagator(shape, z, wavelength, pitch, padding="2x")
    minus = Propagator(shape, -z, wavelength, pitch, padding="2x")
    assert torch.equal(transfer_function(minus.plan, torch.complex128),
                       transfer_function(plus.plan, torch.complex128).conj())
    # A smooth blob in the middle stays inside the window, so the crop loses nothing.
    y = torch.arange(shape[0], dtype=torch.float64)[:, None] - shape[0] / 2
    x = torch.arange(shape[1], dtype=torch.float64)[None, :] - shape[1] / 2
    field = torch.exp(-(y**2 + x**2) / 36.0) * torch.exp(0.3j * x - 0.2j * y)
    forward = plus(field)
    assert _rel(forward, field) > 0.3
    assert _rel(minus(forward), field) < 1e-9


@pytest.mark.parametrize("distance", [0.5, -2.0])
def test_band_limit_keeps_under_ten_percent(distance):
    field = _random_field((48, 64), seed=1)
    for padding in ("auto", "none", "2x"):
        plan = plan_propagation((48, 64), distance, 680e-9, 3.74e-6, padding=padding)
        assert plan.passed_fraction[0] * plan.passed_fraction[1] < 0.1
        out = propagate(field, distance, 680e-9, 3.74e-6, padding=padding)
        assert bool(torch.isfinite(torch.view_as_real(out)).all())
        assert _energy(out) <= _energy(field) * (1 + 1e-12)
        assert _energy(out) > 0


def test_evanescent_frequencies_are_zeroed():
    # 0.2 um pitch at 680 nm: the grid holds frequencies up to 2.5 / um, light propagates only below 1.47 / um.
    shape, pitch, wavelength, z = (40, 56), 0.2e-6, 680e-9, 3e-6
    field = _random_field(shape, seed=2)
    out = propagate(field, z, wavelength, pitch, padding="none")
    assert bool(torch.isfinite(torch.view_as_real(out)).all())
    fy = torch.fft.fftfreq(shape[0], d=pitch, dtype=torch.float64)[:, None]
    fx = torch.fft.fftfreq(shape[1], d=pitch, dtype=torch.float64)[None, :]
    evanescent = fy**2 + fx**2 >= 1 / wavelength**2
    assert 0.2 < float(evanescent.double().mean()) < 0.9
    spectrum = torch.fft.fft2(out)
    assert float(spectrum[evanescent].abs().max()) < 1e-12 * float(spectrum.abs().max())
    # The propagating part is untouched in modulus: evanescent light is removed, nothing else is.
    source = torch.fft.fft2(field)
    passed = ~evanescent & (transfer_function(plan_propagation(shape, z, wavelength, pitch, padding="none"),
                                              torch.complex128).abs() > 0)
    torch.testing.assert_close(spectrum[passed].abs(), source[passed].abs(), rtol=1e-10, atol=1e-10)
    # With padding the grid carries grazing light: the plan pads the whole grid plus a margin.
    for padding in ("auto", "2x"):
        assert bool(torch.isfinite(torch.view_as_real(propagate(field, z, wavelength, pitch, padding=padding))).all())
    assert plan_propagation(shape, z, wavelength, pitch).spread_px == (math.inf, math.inf)


def _gaussian(shape: tuple[int, int], pitch: tuple[float, float], w0: float, z: float, wavelength: float):
    """Paraxial Gaussian beam at z, centred on pixel (H // 2, W // 2), piston removed."""
    y = (torch.arange(shape[0], dtype=torch.float64) - shape[0] // 2) * pitch[0]
    x = (torch.arange(shape[1], dtype=torch.float64) - shape[1] // 2) * pitch[1]
    q = 1 + 1j * z * wavelength / (math.pi * w0**2)
    return torch.exp(-(y[:, None] ** 2 + x[None, :] ** 2) / (w0**2 * q)) / q


@pytest.mark.parametrize("shape", [(31, 57), (57, 31), (45, 45), (33, 64)])
def test_non_square_and_odd_sizes(shape):
    pitch, wavelength, z, w0 = (5e-6, 7e-6), 520e-9, 2e-3, 20e-6
    start = _gaussian(shape, pitch, w0, 0.0, wavelength)
    for padding in ("auto", "2x", 4):
        out = propagate(start, z, wavelength, pitch, padding=padding)
        assert out.shape == shape
        assert _rel(out, _gaussian(shape, pitch, w0, z, wavelength)) < 1e-3
    # A batch of odd fields is propagated like each field alone.
    batch = _random_field((3, *shape), seed=3)
    together = propagate(batch, z, wavelength, pitch)
    alone = torch.stack([propagate(f, z, wavelength, pitch) for f in batch])
    assert _rel(together, alone) < 1e-12


def test_one_by_one_and_two_by_two_fields():
    pitch, wavelength, z = 8e-6, 520e-9, 1e-3
    one = torch.full((1, 1), 0.5 + 0.5j, dtype=torch.complex128)
    assert torch.equal(propagate(one, z, wavelength, pitch, padding="none"), one)  # only f = 0 exists
    for padding in ("auto", "2x"):
        out = propagate(one, z, wavelength, pitch, padding=padding)
        assert out.shape == (1, 1) and bool(torch.isfinite(torch.view_as_real(out)).all())
        assert 0 < abs(complex(out)) <= abs(complex(one))
    # 2 x 2 without padding: frequencies 0 and -1 / (2 pitch) per axis, computed here with numpy.
    two = _random_field((2, 2), seed=4)
    f = np.fft.fftfreq(2, d=pitch)
    limit = 1 / (wavelength * math.sqrt((2 * z / (2 * pitch)) ** 2 + 1))
    f2 = f[:, None] ** 2 + f[None, :] ** 2
    kernel = np.exp(2j * np.pi * z * (np.sqrt(1 / wavelength**2 - f2) - 1 / wavelength))
    kernel *= (np.abs(f[:, None]) < limit) & (np.abs(f[None, :]) < limit)
    expected = np.fft.ifft2(np.fft.fft2(two.numpy()) * kernel)
    np.testing.assert_allclose(propagate(two, z, wavelength, pitch, padding="none").numpy(), expected, atol=1e-12)
    for padding in ("auto", "2x", 1):
        out = propagate(two, z, wavelength, pitch, padding=padding)
        assert out.shape == (2, 2) and _energy(out) <= _energy(two) * (1 + 1e-12)


def test_float32_matches_float64_at_200mm_450nm():
    # The kernel phase reaches ~1e4 rad here; cast to float32 with the piston in, it would be off by ~0.1 rad.
    field = _random_field((96, 128), seed=5)
    out64 = propagate(field, 0.2, 450e-9, 3.74e-6)
    out32 = propagate(field.to(torch.complex64), 0.2, 450e-9, 3.74e-6)
    assert out32.dtype == torch.complex64
    assert _rel(out32, out64) < 1e-4


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf"), complex(0, float("nan")),
                                 complex(1, float("inf"))])
def test_nan_or_inf_input_raises(bad):
    field = torch.ones(2, 8, 8, dtype=torch.complex64)
    field[1, 3, 5] = bad
    with pytest.raises(ValueError, match="NaN or inf"):
        propagate(field, 1e-3, 520e-9, 8e-6)
    with pytest.raises(ValueError, match="NaN or inf"):
        Propagator((8, 8), 1e-3, 520e-9, 8e-6)(field)
    real = torch.ones(8, 8)
    real[0, 0] = bad.real if isinstance(bad, complex) and math.isfinite(bad.imag) else float("nan")
    with pytest.raises(ValueError, match="NaN or inf"):
        propagate(real, 1e-3, 520e-9, 8e-6)
    # Large but finite values whose sum overflows float32 are fine.
    huge = torch.full((8, 8), 3e38, dtype=torch.complex64)
    assert bool(torch.isfinite(torch.view_as_real(propagate(huge, 0.0, 520e-9, 8e-6))).all())
    with pytest.raises(ValueError, match=r"\(\.\.\., H, W\)"):
        propagate(torch.ones(8, dtype=torch.complex64), 1e-3, 520e-9, 8e-6)


def test_finite_gradients_at_zero_amplitude():
    shape = (24, 32)
    amplitude = torch.zeros(shape, dtype=torch.float64)
    amplitude[8:16, 10:20] = 1.0
    amplitude.requires_grad_(True)
    phase = torch.zeros(shape, dtype=torch.float64, requires_grad=True)
    for dtype in (torch.complex64, torch.complex128):
        field = torch.polar(amplitude, phase).to(dtype)
        out = propagate(field, 1e-3, 520e-9, 8e-6)
        loss = out.abs().sum() + propagate(torch.zeros_like(field), 1e-3, 520e-9, 8e-6).abs().sum()
        assert float(out.detach().abs().min()) < 1e-3  # the output has (near-)zeros too
        grads = torch.autograd.grad(loss, (amplitude, phase))
        for grad in grads:
            assert bool(torch.isfinite(grad).all())
        assert float(grads[0].abs().sum()) > 0


def test_first_use_under_inference_mode_does_not_poison_the_cache():
    prop = Propagator((32, 48), 0.01, 520e-9, 8e-6)
    field = torch.polar(torch.ones(32, 48), torch.linspace(0, 3, 32 * 48).reshape(32, 48))
    with torch.inference_mode():
        first = prop(field)
    phase = torch.zeros(32, 48, requires_grad=True)
    prop(field * torch.polar(torch.ones_like(phase), phase)).abs().sum().backward()
    assert torch.isfinite(phase.grad).all() and phase.grad.abs().sum() > 0
    assert torch.equal(prop(field), first)
