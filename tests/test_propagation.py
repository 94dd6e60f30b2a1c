"""Angular-spectrum propagation against references that are not the code: analytic beams, a direct
Rayleigh-Sommerfeld integral, Parseval, float64 and heavily padded propagations."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest
import torch

import benchctl.optics.propagation as propagation
from benchctl.calibration.geometry import describe_plans
from benchctl.calibration.setups import optical_setup
from benchctl.optics import Propagator, PrunedPropagator, plan_propagation, propagate
from benchctl.optics.plan import wrapped_tail_power
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import load_profile


def _rel(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.linalg.vector_norm(a.to(b.dtype) - b) / torch.linalg.vector_norm(b))


def _coords(n: int, pitch: float) -> torch.Tensor:
    """Sample positions along one axis, 0 at pixel n // 2."""
    return (torch.arange(n, dtype=torch.float64) - n // 2) * pitch


def _random_phase(shape: tuple[int, int], seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    phase = (2 * torch.rand(shape, generator=generator, dtype=torch.float64) - 1) * math.pi
    return torch.polar(torch.ones_like(phase), phase)


def _centroid(field: torch.Tensor) -> tuple[float, float]:
    intensity = field.abs().square()
    rows = torch.arange(field.shape[-2], dtype=torch.float64)[:, None]
    cols = torch.arange(field.shape[-1], dtype=torch.float64)[None, :]
    total = intensity.sum()
    return float((intensity * rows).sum() / total), float((intensity * cols).sum() / total)


def _paraxial_gaussian(y: torch.Tensor, x: torch.Tensor, w0: float, z: float, wavelength: float,
                       tilt_fx: float = 0.0) -> torch.Tensor:
    """Fresnel propagation of exp(-r^2 / w0^2) exp(i 2 pi tilt_fx x) over z, piston k z removed."""
    q = 1 + 1j * z * wavelength / (math.pi * w0**2)
    xs = x[None, :] - wavelength * z * tilt_fx
    envelope = torch.exp(-(xs**2 + y[:, None] ** 2) / (w0**2 * q)) / q
    return envelope * torch.exp(1j * (2 * math.pi * tilt_fx * x[None, :] - math.pi * wavelength * z * tilt_fx**2))


@pytest.mark.parametrize("distance", [10e-3, -10e-3])
def test_gaussian_beam_matches_paraxial_analytic(distance):
    (h, w), pitch, wavelength, w0 = (96, 128), 4e-6, 520e-9, 40e-6
    y, x = _coords(h, pitch), _coords(w, pitch)
    start = _paraxial_gaussian(y, x, w0, 0.0, wavelength)
    out = propagate(start, distance, wavelength, pitch)
    assert out.dtype == torch.complex128
    assert _rel(out, _paraxial_gaussian(y, x, w0, distance, wavelength)) < 1e-4
    # The analytic beam of the opposite sign is far away: the test sees a sign error.
    assert _rel(out, _paraxial_gaussian(y, x, w0, -distance, wavelength)) > 0.5


def _rayleigh_sommerfeld(source, xs, ys, step, out_x, out_y, z, wavelength):
    """First Rayleigh-Sommerfeld integral by direct quadrature, float64, with the piston k z removed."""
    k = 2 * math.pi / wavelength
    sx = xs[None, :].expand(len(ys), -1).reshape(-1)
    sy = ys[:, None].expand(-1, len(xs)).reshape(-1)
    weights = source.reshape(-1) * step * step / (2 * math.pi)
    result = torch.empty(len(out_y), len(out_x), dtype=torch.complex128)
    for i, yo in enumerate(out_y):
        r = torch.sqrt((out_x[:, None] - sx) ** 2 + (yo - sy) ** 2 + z * z)
        kernel = (z / r) * (1 / r - 1j * k) * torch.exp(1j * k * (r - z)) / r
        result[i] = kernel @ weights
    return result


def test_matches_rayleigh_sommerfeld_integral_non_paraxial():
    # A beam tilted by 14.5 degrees at half-wavelength pitch: the Fresnel approximation is off by > 1 %.
    n, pitch, wavelength, z, w0 = 64, 0.5e-6, 0.5e-6, 20e-6, 2.5e-6
    tilt = 0.25 / wavelength

    def beam(x, y):
        return torch.exp(-(x[None, :] ** 2 + y[:, None] ** 2) / w0**2) * torch.exp(2j * math.pi * tilt * x[None, :])

    grid = _coords(n, pitch)
    out = propagate(beam(grid, grid), z, wavelength, pitch)
    # The quadrature samples the continuous beam twice per pixel; compare where the beam lands.
    step = pitch / 2
    src = torch.arange(-9e-6, 9e-6 + step / 2, step, dtype=torch.float64)
    rows, cols = slice(n // 2 - 16, n // 2 + 16), slice(n // 2 - 8, n // 2 + 24)
    expected = _rayleigh_sommerfeld(beam(src, src), src, src, step, grid[cols], grid[rows], z, wavelength)
    assert _rel(out[rows, cols], expected) < 1e-5
    assert _rel(_paraxial_gaussian(grid, grid, w0, z, wavelength, tilt)[rows, cols], expected) > 1e-2


def test_energy_conserved_for_band_limited_field():
    (h, w), pitch, wavelength, z = (64, 96), 8e-6, 520e-9, 20e-3
    generator = torch.Generator().manual_seed(1)
    spectrum = torch.randn(h, w, dtype=torch.complex128, generator=generator)
    fy = torch.fft.fftfreq(h, d=pitch, dtype=torch.float64)[:, None]
    fx = torch.fft.fftfreq(w, d=pitch, dtype=torch.float64)[None, :]
    # Matsushima's limit for the unpadded grid, written out here; keep well inside it.
    limit = [1 / (wavelength * math.sqrt((2 * z / (m * pitch)) ** 2 + 1)) for m in (h, w)]
    spectrum = spectrum * ((fy.abs() < 0.9 * limit[0]) & (fx.abs() < 0.9 * limit[1]))
    field = torch.fft.ifft2(spectrum)
    out = propagate(field, z, wavelength, pitch, padding="none")
    energy_in, energy_out = field.abs().square().sum(), out.abs().square().sum()
    assert float(abs(energy_out / energy_in - 1)) < 1e-12
    assert _rel(out, field) > 0.1  # it did propagate


def _inside_field(shape: tuple[int, int], pitch: float) -> torch.Tensor:
    """Three tilted Gaussians well inside the grid: a field that stays in the window over a few mm."""
    y, x = _coords(shape[0], pitch), _coords(shape[1], pitch)
    field = torch.zeros(shape, dtype=torch.complex128)
    for (cy, cx, fy, fx) in ((-5, 0, 0.0, 2e3), (4, -8, -3e3, 0.0), (3, 9, 1e3, -1e3)):
        envelope = torch.exp(-((y[:, None] - cy * pitch) ** 2 + (x[None, :] - cx * pitch) ** 2) / (6 * pitch) ** 2)
        field += envelope * torch.exp(2j * math.pi * (fy * y[:, None] + fx * x[None, :]))
    return field


def test_forward_then_backward_round_trip_restores_field():
    shape, pitch, wavelength, z = (80, 112), 6.4e-6, 638e-9, 5e-3
    field = _inside_field(shape, pitch)
    forward = propagate(field, z, wavelength, pitch)
    assert _rel(forward, field) > 0.3
    assert _rel(propagate(forward, -z, wavelength, pitch), field) < 1e-9


@pytest.mark.parametrize("wavelength", [680e-9, 450e-9], ids=["red", "blue"])
def test_float32_path_matches_float64_at_200mm(wavelength):
    field = _random_phase((128, 128))
    out64 = propagate(field, 0.2, wavelength, 3.74e-6)
    out32 = propagate(field.to(torch.complex64), 0.2, wavelength, 3.74e-6)
    assert out32.dtype == torch.complex64 and out64.dtype == torch.complex128
    assert _rel(out32, out64) < 1e-4


def test_plane_wave_at_fft_frequency_gets_exact_phase():
    (h, w), (dy, dx), wavelength, z = (48, 80), (2e-6, 3e-6), 633e-9, 1e-3
    fy, fx = 5 / (h * dy), -7 / (w * dx)
    y, x = _coords(h, dy), _coords(w, dx)
    wave = torch.exp(2j * math.pi * (fy * y[:, None] + fx * x[None, :]))
    out = propagate(wave, z, wavelength, (dy, dx), padding="none")
    kz = math.sqrt(1 / wavelength**2 - fy**2 - fx**2)
    assert _rel(out, wave * complex(np.exp(2j * math.pi * z * (kz - 1 / wavelength)))) < 1e-9


def test_centred_gaussian_stays_centred_and_tilted_one_moves_as_predicted():
    # A frequency grid half a bin off would move the centred beam by 0.5 z lambda / (N pitch^2) = 1.3 px here.
    n, pitch, wavelength, z, w0 = 64, 2e-6, 680e-9, 1e-3, 16e-6
    grid = _coords(n, pitch)
    out = propagate(_paraxial_gaussian(grid, grid, w0, 0.0, wavelength), z, wavelength, pitch)
    cy, cx = _centroid(out)
    assert abs(cy - n // 2) < 1e-3 and abs(cx - n // 2) < 1e-3
    tilt = 4 / (n * pitch)
    out = propagate(_paraxial_gaussian(grid, grid, w0, 0.0, wavelength, tilt), z, wavelength, pitch)
    sin_theta = wavelength * tilt
    moved = z * sin_theta / math.sqrt(1 - sin_theta**2) / pitch
    cy, cx = _centroid(out)
    assert abs(cy - n // 2) < 1e-3 and abs(cx - n // 2 - moved) < 0.02


def test_band_limit_on_the_right_axis_for_non_square_grid_and_pitch():
    shape, (dy, dx), wavelength, z = (48, 160), (6e-6, 2e-6), 520e-9, 50e-3
    prop = Propagator(shape, z, wavelength, (dy, dx), padding="2x")
    my, mx = prop.plan.padded_shape
    assert (my, mx) == (96, 320)
    fy = np.fft.fftfreq(my, d=dy)[:, None]
    fx = np.fft.fftfreq(mx, d=dx)[None, :]

    def limit(m, d):
        return 1 / (wavelength * math.sqrt((2 * z / (m * d)) ** 2 + 1))

    expected = (np.abs(fy) < limit(my, dy)) & (np.abs(fx) < limit(mx, dx))
    swapped = (np.abs(fy) < limit(mx, dx)) & (np.abs(fx) < limit(my, dy))
    assert (expected != swapped).any()  # the geometry tells the two axes apart
    support = (prop.kernel(torch.complex128, torch.device("cpu")).abs() > 0).numpy()
    np.testing.assert_array_equal(support, expected)
    assert prop.plan.passed_fraction == pytest.approx((expected.any(1).mean(), expected.any(0).mean()))


def test_propagator_caches_kernel_and_gives_identical_results(monkeypatch):
    calls = []
    original = propagation.transfer_function

    def counting(*args, **kwargs):
        calls.append(args)
        return original(*args, **kwargs)

    monkeypatch.setattr(propagation, "transfer_function", counting)
    prop = Propagator((32, 48), 5e-3, 520e-9, 4e-6)
    field = _random_phase((32, 48)).to(torch.complex64)
    first, second = prop(field), prop(field)
    assert torch.equal(first, second)
    assert len(calls) == 1
    assert prop.kernel(torch.complex64, torch.device("cpu")) is prop.kernel(torch.complex64, "cpu")
    # The reused work buffer carries nothing over from one call to the next, whatever the batch shape.
    other = _random_phase((3, 32, 48), seed=9).to(torch.complex64)
    fresh = Propagator((32, 48), 5e-3, 520e-9, 4e-6)
    assert torch.equal(prop(other), fresh(other)) and torch.equal(prop(field), first)
    # The result owns just its own pixels, not the padded grid it was cut from.
    assert first.is_contiguous() and first.untyped_storage().nbytes() == first.numel() * first.element_size()


@pytest.mark.parametrize(
    "padding, padded",
    [("none", (40, 56)), ("2x", (80, 112)), ("4x", (160, 224)), (5, (50, 66)), (0, (40, 56))],
)
def test_plan_describes_padding_for_each_mode(padding, padded):
    plan = plan_propagation((40, 56), 2e-3, 520e-9, 8e-6, padding=padding)
    assert plan.padded_shape == padded
    text = plan.describe()
    assert f"padding={padding}" in text and f"40x56 -> {padded[0]}x{padded[1]}" in text


def _is_fast_size(m: int) -> bool:
    if m % 4:
        return False
    for p in (2, 3, 5, 7):
        while m % p == 0:
            m //= p
    return m == 1


@pytest.mark.parametrize(
    "shape, z", [((270, 480), 8.75e-3), ((270, 480), 2e-3), ((64, 200), 5e-3), ((2160, 3840), 0.07)]
)
def test_auto_guard_covers_the_reach_plus_a_margin_and_never_exceeds_2x(shape, z):
    guards = []
    for wavelength in (450e-9, 520e-9, 680e-9):  # growing reach
        plan = plan_propagation(shape, z, wavelength, 3.74e-6, padding="auto")
        for n, m, k in zip(plan.shape, plan.padded_shape, plan.spread_px):
            assert m - n >= min(k, n) and (m - n > k or m - n >= n)
            assert _is_fast_size(m) and m < 2 * n + 64
        guards.append(tuple(m - n for n, m in zip(plan.shape, plan.padded_shape)))
        assert plan.pad == (0, guards[-1][0], 0, guards[-1][1])
    assert guards == sorted(guards)


def test_wrapped_tail_power_sums_every_source_output_pair():
    n, reach, guard = 23, 9.5, 14
    total = 0.0
    for a in range(n):  # output a pixels inside one edge, source b pixels inside the other
        for b in range(n):
            d = guard + 1 + a + b
            total += ((1 / (d - reach) - 1 / (d + reach)) / (2 * math.pi)) ** 2
    assert wrapped_tail_power(n, reach, guard) == pytest.approx(2 * total / n, rel=1e-12)


def test_bad_padding_is_refused():
    for padding in ("3", "x", "0x", -1, True, 2.0):
        with pytest.raises(ValueError, match="padding"):
            plan_propagation((16, 16), 1e-3, 520e-9, 8e-6, padding=padding)


def test_int_padding_equals_manual_zero_padding():
    shape, pad, pitch, wavelength, z = (30, 44), 7, 4e-6, 520e-9, 3e-3
    field = _random_phase(shape, seed=3)
    out = propagate(field, z, wavelength, pitch, padding=pad)
    padded = torch.nn.functional.pad(field, (pad, pad, pad, pad))
    manual = propagate(padded, z, wavelength, pitch, padding="none")[pad:-pad, pad:-pad]
    assert _rel(out, manual) < 1e-12


def test_gradient_matches_finite_difference():
    shape, pitch, wavelength, z = (16, 24), 8e-6, 520e-9, 2e-3
    generator = torch.Generator().manual_seed(4)
    phase = torch.rand(shape, generator=generator, dtype=torch.float64) * 2 * math.pi
    weights = torch.rand(shape, generator=generator, dtype=torch.float64)

    def loss(p: torch.Tensor) -> torch.Tensor:
        return (weights * propagate(torch.polar(torch.ones_like(p), p), z, wavelength, pitch).abs()).sum()

    phase.requires_grad_(True)
    (grad,) = torch.autograd.grad(loss(phase), phase)
    eps = 1e-6
    for index in ((0, 0), (7, 11), (15, 23)):
        step = torch.zeros_like(phase)
        step[index] = eps
        with torch.no_grad():
            numeric = (loss(phase + step) - loss(phase - step)) / (2 * eps)
        assert float(grad[index]) == pytest.approx(float(numeric), rel=1e-6, abs=1e-9)


def _roi(shape: tuple[int, int]) -> tuple[slice, slice]:
    """The paper's ROI (880 x 1600 of 1088 x 1920) scaled to `shape`, centred."""
    rh, rw = round(shape[0] * 880 / 1088), round(shape[1] * 1600 / 1920)
    top, left = (shape[0] - rh) // 2, (shape[1] - rw) // 2
    return slice(top, top + rh), slice(left, left + rw)


def _roi_errors(shape, z, wavelength, modes):
    """Relative L2 error on the ROI of a random-phase field (complex64) against an 8x padded float64 run."""
    pitch = 3.74e-6
    field = _random_phase(shape, seed=5)
    rows, cols = _roi(shape)
    reference = propagate(field, z, wavelength, pitch, padding="8x")[rows, cols]
    return {mode: _rel(propagate(field.to(torch.complex64), z, wavelength, pitch, padding=mode)[rows, cols],
                       reference) for mode in modes}


@pytest.mark.slow
@pytest.mark.parametrize("wavelength", [680e-9, 520e-9, 450e-9], ids=["red", "green", "blue"])
def test_auto_is_within_twice_the_2x_error_on_scaled_paper_geometry(wavelength):
    # The paper's 4K geometry (2160 x 3840, 3.74 um, 70 mm) scaled down 8x in grid and distance: same K / N.
    errors = _roi_errors((270, 480), 70e-3 / 8, wavelength, ("none", "2x", "auto"))
    assert errors["auto"] <= 2 * errors["2x"]
    assert errors["2x"] < 0.05 < errors["none"]


@pytest.mark.slow
@pytest.mark.parametrize("wavelength", [680e-9, 450e-9], ids=["red", "blue"])
def test_auto_pads_much_less_than_2x_where_spread_is_small(wavelength):
    shape, z = (270, 480), 2e-3  # K / N between 0.07 and 0.18
    auto, double = (plan_propagation(shape, z, wavelength, 3.74e-6, padding=m) for m in ("auto", "2x"))
    assert max(auto.spread_fraction) < 0.2
    assert math.prod(auto.padded_shape) < 0.65 * math.prod(double.padded_shape)
    errors = _roi_errors(shape, z, wavelength, ("2x", "auto"))
    assert errors["auto"] < 1e-2  # a few times AUTO_TOLERANCE's model figure, as measured at 4K


def test_propagation_bench_returns_one_row_per_mode_with_ratios(small_profile_path: Path) -> None:
    from benchctl.benchmarks.propagation import run_propagation_bench

    lines: list[str] = []
    profile = load_profile(small_profile_path)
    green = msgspec.structs.replace(profile, optics=msgspec.structs.replace(profile.optics, distance_mm=2.0),
                                    laser=msgspec.structs.replace(profile.laser, channels=(profile.channel("green"),)))
    rows = run_propagation_bench(green, sizes=[(48, 64)], repeats=1, out=lines.append)
    assert [r["mode"] for r in rows] == ["none", "2x", "auto", "auto+roi"]
    by_mode = {r["mode"]: r for r in rows}
    # the ROI alone, on a smaller grid, with the error of the whole field's "auto" (the same outputs)
    assert by_mode["auto+roi"]["roi_rel_l2"] == pytest.approx(by_mode["auto"]["roi_rel_l2"], rel=1e-3)
    roi_rows, roi_cols = map(int, by_mode["auto+roi"]["padded"].split("x"))
    auto_rows, auto_cols = map(int, by_mode["auto"]["padded"].split("x"))
    assert roi_rows * roi_cols < auto_rows * auto_cols
    assert by_mode["2x"]["speedup_vs_2x"] == 1.0 and by_mode["2x"]["error_vs_2x"] == 1.0
    assert by_mode["2x"]["roi_rel_l2"] < by_mode["none"]["roi_rel_l2"]
    assert all(r["time_ms"] > 0 and r["bare_fft_ms"] > 0 and r["plan"] for r in rows)
    assert any("auto vs 2x" in line for line in lines) and any("K/N rows" in line for line in lines)
    rows = run_propagation_bench(green, sizes=[(16, 24)], modes=(3, "auto"), repeats=1, out=lines.append)
    assert [r["mode"] for r in rows] == ["3", "auto"] and rows[0]["speedup_vs_2x"] is None
    assert {r["colour"] for r in rows} == {"green"} and rows[0]["size"] == "16x24"


@pytest.mark.parametrize(
    "shape, distance_m, expected",
    [
        # REFERENCE.md: 3.74 um, 2x padding, 1088 rows at 7 cm keeps 0.64 (680 nm) to 0.96 (450 nm) of the
        # (2-D) frequencies; at 20 cm 0.09 to 0.20; a 2160-row grid at 7 cm keeps everything.
        ((1088, 1920), 0.07, (0.64, 0.96)),
        ((1088, 1920), 0.20, (0.09, 0.20)),
        ((2160, 3840), 0.07, (1.00, 1.00)),
    ],
)
def test_band_limit_fractions_match_published_figures(shape, distance_m, expected):
    red = math.prod(plan_propagation(shape, distance_m, 680e-9, 3.74e-6, padding="2x").passed_fraction)
    blue = math.prod(plan_propagation(shape, distance_m, 450e-9, 3.74e-6, padding="2x").passed_fraction)
    assert red == pytest.approx(expected[0], abs=0.01)
    assert blue == pytest.approx(expected[1], abs=0.01)


def _plane_wave(shape, cycles):
    rows, cols = torch.meshgrid(torch.arange(shape[0], dtype=torch.float64),
                                torch.arange(shape[1], dtype=torch.float64), indexing="ij")
    phase = 2 * math.pi * (cycles[0] * rows / shape[0] + cycles[1] * cols / shape[1])
    return torch.polar(torch.ones(shape, dtype=torch.float64), phase)


def test_aperture_passes_frequencies_inside_the_iris_and_blocks_those_outside():
    shape, pitch, lam = (64, 64), 8e-6, 520e-9
    # 8 cycles over 64 px is 0.25 of Nyquist, 24 cycles is 0.75 of Nyquist.
    slow, fast = _plane_wave(shape, (8, 0)), _plane_wave(shape, (0, 24))
    kw = dict(padding="none", aperture=0.5)
    out_slow = propagate(slow, 1e-3, lam, pitch, **kw)
    out_fast = propagate(fast, 1e-3, lam, pitch, **kw)
    assert torch.allclose(out_slow.abs(), torch.ones(shape, dtype=torch.float64), atol=1e-9)
    assert out_fast.abs().max() < 1e-9


def test_aperture_wider_than_the_spectrum_changes_nothing():
    field = torch.polar(torch.ones(48, 40), torch.rand(48, 40, generator=torch.Generator().manual_seed(3)) * 6)
    # The spectrum's corner sits at sqrt(2) x Nyquist: an iris of 1.5 passes everything.
    wide = propagate(field, 5e-3, 450e-9, 4e-6, aperture=1.5)
    assert torch.equal(wide, propagate(field, 5e-3, 450e-9, 4e-6))


def test_aperture_at_zero_distance_low_passes_instead_of_identity():
    field = _plane_wave((32, 32), (0, 12)) + _plane_wave((32, 32), (2, 0))
    out = Propagator((32, 32), 0.0, 520e-9, 8e-6, padding="none", aperture=0.5)(field)
    assert torch.allclose(out, _plane_wave((32, 32), (2, 0)), atol=1e-9)


def test_aperture_must_be_positive():
    with pytest.raises(ValueError, match="aperture"):
        plan_propagation((8, 8), 1e-3, 520e-9, 8e-6, aperture=0.0)


@pytest.mark.parametrize("name", ["simulated", "simulated-aberrated", "paper_bench"])
def test_a_profiles_described_plans_are_its_setups_plans(name: str) -> None:
    # `profile check` plans without torch; what it prints must be what generation will compute.
    profile = load_profile(name)
    text = describe_plans(profile)
    for channel in profile.channels:
        plan = optical_setup(profile, channel.name).target_propagator().plan
        assert f"    {channel.name}: {plan.describe()}" in text.splitlines()


@pytest.mark.parametrize(("shape", "window", "padding", "aperture", "distance_m"), [
    ((96, 128), (28, 40, 34, 60), "auto", None, 0.02),
    ((97, 131), (33, 31, 27, 77), "auto", 0.5, 0.05),  # odd sizes, an iris
    ((64, 96), (0, 10, 86, 10), "2x", 0.7, 0.02),  # a window in a corner
    ((64, 96), (5, 40, 7, 50), "none", None, -0.03),  # the whole plan wraps; backwards
])
def test_a_windowed_propagation_gives_the_whole_fields_outputs_on_a_smaller_grid(shape, window, padding,
                                                                                 aperture, distance_m) -> None:
    field = torch.polar(torch.rand(shape, dtype=torch.float64) + 0.5,
                        torch.rand(shape, dtype=torch.float64) * 2 * math.pi)
    whole = Propagator(shape, distance_m, 520e-9, 8e-6, padding=padding, aperture=aperture)
    windowed = Propagator(shape, distance_m, 520e-9, 8e-6, padding=padding, aperture=aperture, window=window)
    row, rows, col, cols = window
    expected = whole(field)[row:row + rows, col:col + cols]
    got = windowed(field)
    assert got.shape == (rows, cols) and got.dtype == torch.complex128
    assert float((got - expected).abs().max()) < 1e-12 * float(expected.abs().max())
    (ph, pw), (wh, ww) = whole.plan.padded_shape, windowed.plan.padded_shape
    assert windowed.plan.kernel_shape == (ph, pw) and wh <= ph and ww <= pw
    assert wh * ww < ph * pw or padding == "none"
    single = windowed(field.to(torch.complex64))  # the folded kernel is built in float64, then cast
    assert float((single - expected).abs().max()) < 1e-5 * float(expected.abs().max())


def test_a_window_needs_rows_plus_field_minus_one_samples_per_axis() -> None:
    plan = Propagator((100, 200), 0.05, 520e-9, 8e-6, padding="2x", window=(30, 40, 0, 200)).plan
    assert plan.padded_shape == (140, 400)  # 100 + 40 - 1 = 139 -> 140; 200 + 200 - 1 > 2x's 400 -> 400
    assert "output window 40x200" in plan.describe()
    with pytest.raises(ValueError, match=r"window \(90, 20, 0, 10\) .* does not fit in the field \(100, 200\)"):
        Propagator((100, 200), 0.05, 520e-9, 8e-6, window=(90, 20, 0, 10))


def test_reconstruct_roi_is_the_roi_of_reconstruct_and_keeps_the_gradient() -> None:
    setup = OpticalSetup(wavelength_m=520e-9, pitch_m=8e-6, distance_m=0.02, shape=(64, 96), roi=(30, 50),
                         aperture=0.6)
    phase = (torch.rand(64, 96, dtype=torch.float64) * 2 * math.pi).requires_grad_()
    rows, cols = setup.roi_slices
    whole = setup.reconstruct(phase)[rows, cols]
    roi = setup.reconstruct_roi(phase)
    assert torch.allclose(roi, whole, rtol=0, atol=1e-12)
    (grad_whole,) = torch.autograd.grad(whole.square().sum(), phase)
    (grad_roi,) = torch.autograd.grad(roi.square().sum(), phase)
    assert torch.allclose(grad_roi, grad_whole, rtol=0, atol=1e-10)
    assert setup.roi_propagator() is setup.roi_propagator()


@pytest.mark.parametrize("aperture, window", [(0.5, None), (None, None), (0.3, (5, 40, 10, 60))])
def test_the_pruned_evaluation_is_the_propagators_to_float32_rounding(aperture, window):
    """PrunedPropagator skips the guard band's rows, the frequencies the transfer function zeroes and the outputs
    outside the window, and must give what the propagator gives."""
    propagator = Propagator((64, 96), 20e-3, 520e-9, 8e-6, aperture=aperture, window=window)
    gen = torch.Generator().manual_seed(3)
    field = torch.polar(torch.rand(64, 96, generator=gen), 2 * math.pi * torch.rand(64, 96, generator=gen))
    expected = propagator(field.to(torch.complex64))
    got = PrunedPropagator(propagator)(field.to(torch.complex64))
    assert got.shape == expected.shape
    assert float((got - expected).abs().max()) < 1e-5 * float(expected.abs().max())
