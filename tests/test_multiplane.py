"""Propagation to several planes against references that are not the code: a direct per-plane angular-spectrum
propagation written here in numpy float64, a Gaussian beam diverging from a point behind the SLM (its analytic
spherical-wavefront beam at every plane), and Parseval."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchctl.optics import MultiPlanePropagator, plan_propagation
from benchctl.optics.fitted import FittedOptics
from benchctl.optics.setup import OpticalSetup


def _reference(field: np.ndarray, z: float, wavelength: float, pitch: float, factor: int = 2,
               iris: float | None = None) -> np.ndarray:
    """Band-limited ASM in float64, padded `factor` x, the piston e^(i k z) divided out afterwards."""
    h, w = field.shape
    m_y, m_x = factor * h, factor * w
    padded = np.zeros((m_y, m_x), dtype=np.complex128)
    padded[:h, :w] = field
    fy = np.fft.fftfreq(m_y, d=pitch)[:, None]
    fx = np.fft.fftfreq(m_x, d=pitch)[None, :]
    root = 1 / wavelength**2 - fy**2 - fx**2
    transfer = np.exp(2j * np.pi * z * np.sqrt(np.maximum(root, 0.0))) * (root > 0)
    # Matsushima & Shimobaba's limit per axis, for this padded extent
    limit_y = 1 / (wavelength * math.sqrt((2 * z / (m_y * pitch)) ** 2 + 1))
    limit_x = 1 / (wavelength * math.sqrt((2 * z / (m_x * pitch)) ** 2 + 1))
    transfer = transfer * ((np.abs(fy) < limit_y) & (np.abs(fx) < limit_x))
    if iris is not None:
        transfer = transfer * ((2 * pitch * fy) ** 2 + (2 * pitch * fx) ** 2 < iris**2)
    out = np.fft.ifft2(np.fft.fft2(padded) * transfer)[:h, :w]
    return out * np.exp(-2j * np.pi * z / wavelength)


def _relative(a: torch.Tensor | np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(a, dtype=np.complex128) - b) / np.linalg.norm(b))


def _random_phase(shape: tuple[int, int], seed: int = 0) -> np.ndarray:
    return np.exp(2j * np.pi * np.random.default_rng(seed).random(shape))


DISTANCES = (4e-3, 9e-3, 6.5e-3, 15e-3, -7e-3)


@pytest.mark.parametrize("iris", [None, 0.6])
def test_every_plane_matches_an_independent_float64_propagation(iris):
    shape, pitch, wavelength = (48, 80), 6.4e-6, 520e-9
    field = _random_phase(shape)
    propagator = MultiPlanePropagator(shape, DISTANCES, wavelength, pitch, padding="2x", aperture=iris)
    out = propagator(torch.from_numpy(field).to(torch.complex64))
    assert out.shape == (len(DISTANCES), *shape) and out.dtype == torch.complex64
    for k, z in enumerate(DISTANCES):
        expected = _reference(field, z, wavelength, pitch, iris=iris)
        assert _relative(out[k], expected) < 1e-4, z
        # the planes are told apart: the neighbour's reference is far off
        assert _relative(out[k], _reference(field, DISTANCES[k - 1], wavelength, pitch, iris=iris)) > 0.3


def test_window_computes_the_same_outputs_as_the_whole_field():
    shape, pitch, wavelength, window = (48, 80), 6.4e-6, 638e-9, (10, 24, 16, 40)
    field = torch.from_numpy(_random_phase(shape, seed=3))
    whole = MultiPlanePropagator(shape, DISTANCES, wavelength, pitch, padding="2x")(field)
    windowed = MultiPlanePropagator(shape, DISTANCES, wavelength, pitch, padding="2x", window=window)
    assert windowed.output_shape == (24, 40)
    assert windowed.plan.padded_shape[0] < 96  # a smaller grid than the whole field's
    row, rows, col, cols = window
    torch.testing.assert_close(windowed(field), whole[:, row:row + rows, col:col + cols], rtol=0, atol=1e-12)
    for k, z in enumerate(DISTANCES):  # and the float64 reference, cropped
        expected = _reference(field.numpy(), z, wavelength, pitch)[row:row + rows, col:col + cols]
        assert _relative(windowed(field)[k], expected) < 1e-9


def _diverging_gaussian(shape: tuple[int, int], pitch: float, wavelength: float, w0: float, z: float) -> np.ndarray:
    """A paraxial Gaussian beam of waist w0 at z = 0 (a point source of that size), seen at z: its spherical
    wavefront of radius z + z_R^2 / z and its Gouy phase in the complex q = z - i z_R (waves e^(i(kz - wt))); piston
    e^(i k z) left out."""
    y = (np.arange(shape[0]) - shape[0] // 2)[:, None] * pitch
    x = (np.arange(shape[1]) - shape[1] // 2)[None, :] * pitch
    q0 = -1j * math.pi * w0**2 / wavelength
    q = z + q0
    return (q0 / q) * np.exp(1j * math.pi * (x**2 + y**2) / (wavelength * q))


def test_point_source_spherical_wave_at_every_plane_with_auto_padding():
    # The source sits 3 mm behind the SLM: the SLM sees a diverging spherical wave, which every plane must continue.
    shape, pitch, wavelength, w0, behind = (96, 128), 4e-6, 520e-9, 30e-6, 3e-3
    distances = (2e-3, 5e-3, 8e-3, 12e-3)
    slm = _diverging_gaussian(shape, pitch, wavelength, w0, behind)
    propagator = MultiPlanePropagator(shape, distances, wavelength, pitch)
    # the shared grid is the one "auto" gives the farthest plane
    assert propagator.plan.padded_shape == plan_propagation(shape, max(distances), wavelength, pitch).padded_shape
    out = propagator(torch.from_numpy(slm).to(torch.complex64))
    for k, z in enumerate(distances):
        expected = _diverging_gaussian(shape, pitch, wavelength, w0, behind + z)
        assert _relative(out[k], expected) < 1e-4, z
        assert _relative(out[k], _diverging_gaussian(shape, pitch, wavelength, w0, behind + 1.2 * z)) > 1e-2


def test_energy_is_conserved_at_every_plane_where_nothing_is_cut():
    (h, w), pitch, wavelength = (64, 96), 8e-6, 520e-9
    distances = (5e-3, 20e-3, -12e-3)
    rng = np.random.default_rng(1)
    spectrum = rng.normal(size=(h, w)) + 1j * rng.normal(size=(h, w))
    fy = np.fft.fftfreq(h, d=pitch)[:, None]
    fx = np.fft.fftfreq(w, d=pitch)[None, :]
    # keep well inside the band limit of the farthest plane on the unpadded grid: no plane cuts anything
    limit = [1 / (wavelength * math.sqrt((2 * 20e-3 / (m * pitch)) ** 2 + 1)) for m in (h, w)]
    field = np.fft.ifft2(spectrum * ((np.abs(fy) < 0.9 * limit[0]) & (np.abs(fx) < 0.9 * limit[1])))
    out = MultiPlanePropagator((h, w), distances, wavelength, pitch, padding="none")(torch.from_numpy(field))
    energy = float(np.sum(np.abs(field) ** 2))
    for k in range(len(distances)):
        assert abs(float(out[k].abs().square().sum()) / energy - 1) < 1e-12
        assert _relative(out[k], field) > 0.1  # it did propagate


def test_batches_and_gradients_match_independent_planes():
    shape, pitch, wavelength, distances = (32, 48), 6.4e-6, 450e-9, (3e-3, 6e-3)
    setups = [OpticalSetup(wavelength, pitch, z, shape, (16, 24), padding="2x") for z in distances]
    phase = torch.rand((2, *shape), generator=torch.Generator().manual_seed(0)) * 6
    weights = torch.rand((2, len(distances), *shape), generator=torch.Generator().manual_seed(1))
    many = phase.clone().requires_grad_()
    stack = setups[0].reconstruct_planes(many, distances)
    assert stack.shape == (2, len(distances), *shape)
    (stack * weights).sum().backward()
    one = phase.clone().requires_grad_()
    separate = torch.stack([s.reconstruct(one) for s in setups], dim=1)
    (separate * weights).sum().backward()
    torch.testing.assert_close(stack, separate, rtol=0, atol=2e-5)
    assert many.grad is not None and one.grad is not None
    torch.testing.assert_close(many.grad, one.grad, rtol=0, atol=1e-3 * float(one.grad.abs().max()))


def test_setup_focal_stack_applies_the_fitted_model_and_display_as_in_2d():
    shape, roi, pitch, wavelength = (40, 56), (24, 32), 6.4e-6, 520e-9
    model = FittedOptics((("defocus", 0.3), ("coma_vertical", -0.2)), waist_m=150e-6, zero_order=0.05)

    def display(phase: torch.Tensor) -> torch.Tensor:  # an 8-level panel
        return torch.round(phase / (2 * math.pi / 8)) * (2 * math.pi / 8)

    setup = OpticalSetup.of(OpticalSetup(wavelength, pitch, 5e-3, shape, roi), model).with_display(display)
    phase = torch.rand(shape, generator=torch.Generator().manual_seed(2)) * 6
    distances = (4e-3, 5e-3, 7e-3)
    stack = setup.reconstruct_planes(phase, distances)
    roi_stack = setup.reconstruct_planes_roi(phase, distances)
    rows, cols = setup.roi_slices
    for k, z in enumerate(distances):
        single = setup.at_distance(z)
        assert single.field_model == model and single.display is display
        torch.testing.assert_close(stack[k], single.reconstruct(phase), rtol=0, atol=1e-5)
        torch.testing.assert_close(roi_stack[k], single.reconstruct(phase)[rows, cols], rtol=0, atol=1e-5)
    assert setup.at_distance(5e-3) is setup
    assert setup.planes_propagator(distances, roi=True) is setup.planes_propagator(list(distances), roi=True)
    with pytest.raises(ValueError, match="non-empty"):
        setup.reconstruct_planes(phase, [])


def test_multiplane_bench_compares_one_stack_with_independent_planes(small_profile_path):
    import msgspec

    from benchctl.benchmarks.propagation import bench_planes, run_multiplane_bench
    from benchctl.profiles import load_profile

    profile = load_profile(small_profile_path)
    green = msgspec.structs.replace(profile, optics=msgspec.structs.replace(profile.optics, depth_range_mm=(15, 25)),
                                    laser=msgspec.structs.replace(profile.laser, channels=(profile.channel("green"),)))
    assert bench_planes(green, 3) == pytest.approx([15e-3, 20e-3, 25e-3])
    lines: list[str] = []
    rows = run_multiplane_bench(green, sizes=[(48, 64)], planes=3, repeats=1, out=lines.append)
    assert len(rows) == 1 and rows[0]["planes"] == 3 and rows[0]["distances_mm"] == "15..25"
    assert rows[0]["ratio"] > 0 and rows[0]["multiplane_ms"] > 0
    # float32 against float64 on the same grid; the shared grid (the farthest plane's) pads nearer planes more than
    # their own would, which moves them by about auto's tolerance
    assert rows[0]["multiplane_rel_l2_shared_grid"] < 1e-5 and rows[0]["independent_rel_l2"] < 1e-5
    assert rows[0]["multiplane_rel_l2"] < 1e-2
    assert any("multi/indep" in line for line in lines)


def test_a_setup_and_its_display_twin_each_move_to_another_distance_with_their_own_display():
    plain = OpticalSetup(520e-9, 6.4e-6, 5e-3, (32, 48), (16, 24))
    assert plain.at_distance(6e-3).display is None  # fills the cache the twin shares

    def display(phase: torch.Tensor) -> torch.Tensor:
        return torch.round(phase)

    shown = plain.with_display(display)
    assert shown.at_distance(6e-3).display is display and plain.at_distance(6e-3).display is None
    assert shown.at_distance(6e-3).distance_m == 6e-3


def test_reused_work_buffers_never_alias_results():
    shape, distances = (24, 32), (3e-3, 5e-3)
    propagator = MultiPlanePropagator(shape, distances, 520e-9, 6.4e-6)
    first_field, second_field = (torch.from_numpy(_random_phase(shape, seed)).to(torch.complex64) for seed in (4, 5))
    first = propagator(first_field)
    kept = first.clone()
    with torch.inference_mode():
        second = propagator(second_field)
    torch.testing.assert_close(first, kept, rtol=0, atol=0)  # the second call left the first result alone
    fresh = MultiPlanePropagator(shape, distances, 520e-9, 6.4e-6)(second_field)
    torch.testing.assert_close(second, fresh, rtol=0, atol=0)
    assert second.shape == (2, *shape)


def test_picked_planes_are_those_planes_of_the_whole_stack_in_the_order_asked():
    shape, pitch, wavelength = (32, 48), 6.4e-6, 520e-9
    distances = (3e-3, 4e-3, 5e-3, 6e-3)
    propagator = MultiPlanePropagator(shape, distances, wavelength, pitch, padding="2x", window=(4, 24, 8, 32))
    field = torch.from_numpy(_random_phase(shape)).to(torch.complex64)
    every = propagator(field)
    torch.testing.assert_close(propagator(field, [3, 0, 2]), every[[3, 0, 2]], rtol=0, atol=0)
    grad_field = field.clone().requires_grad_()
    picked = propagator(grad_field, [1, 3])
    torch.testing.assert_close(picked.detach(), every[[1, 3]], rtol=0, atol=1e-6)
    picked.abs().sum().backward()
    assert grad_field.grad is not None and bool(grad_field.grad.abs().sum() > 0)
    for bad in ([], [4], [-1]):
        with pytest.raises(ValueError, match=r"pick must name planes 0 \.\. 3"):
            propagator(field, bad)


@pytest.mark.slow  # float64 finite differences: 3-6 s on two cores
@pytest.mark.parametrize("window", [None, (3, 8, 5, 10)])
def test_the_gradient_of_the_planes_one_by_one_is_the_finite_difference_one(window):
    """On a CPU under autograd the planes go one at a time both ways (a hand-written adjoint): checked against
    finite differences in float64, batched, picked planes and a window included."""
    shape, distances = (12, 16), (2e-3, 3e-3, 5e-3)
    propagator = MultiPlanePropagator(shape, distances, 520e-9, 6.4e-6, padding="2x", window=window)
    field = torch.from_numpy(np.stack([_random_phase(shape, 1), _random_phase(shape, 2)])).requires_grad_()
    assert torch.autograd.gradcheck(lambda f: propagator(f, [2, 0]), (field,), eps=1e-6, atol=1e-7, rtol=1e-5)
    assert torch.autograd.gradcheck(propagator, (field,), eps=1e-6, atol=1e-7, rtol=1e-5)
