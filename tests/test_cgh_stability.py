"""Hologram methods, classical and learned, on degenerate inputs: black, white, single-pixel, large and non-finite
targets, zero amplitude."""

from __future__ import annotations

import functools
import math

import pytest
import torch

from benchctl.cgh import DPAC, METHODS, Method, Networks, OpticalSetup, check_target, roi_loss
from benchctl.cgh.learned import build_model

# Iterative methods run a few iterations: 10 for the classical ones, 3 for the networks refined by SGD.
ITERATIONS = {"gs": 10, "sgd": 10}


@pytest.fixture(scope="module")
def setup() -> OpticalSetup:
    return OpticalSetup(wavelength_m=520e-9, pitch_m=8e-6, distance_m=20e-3, shape=(64, 64), roi=(48, 48))


def untrained(name: str) -> Networks:
    """Seeded, untrained networks of learned method `name`, one per setup: no shipped checkpoint fits these small
    grids, and stability does not depend on training."""

    @functools.lru_cache(maxsize=None)
    def model(setup: OpticalSetup) -> torch.nn.Module:
        torch.manual_seed(0)
        return build_model(name, setup).eval()

    return lambda setup, device: model(setup)


@pytest.fixture(scope="module")
def methods() -> dict[str, Method]:
    """Every registered method, runnable: those that need a checkpoint get untrained networks."""
    return {name: method.trained(untrained(method.network), "untrained") if method.needs_checkpoint else method
            for name, method in METHODS.items()}


def run_every_method(methods: dict[str, Method], target: torch.Tensor, setup: OpticalSetup) -> dict[str, torch.Tensor]:
    """Each method's phase for `target`, checked to be finite, float32, (H, W) and in [-pi, pi)."""
    return {name: _checked(name, method(target, setup, iterations=_iterations(method)), setup)
            for name, method in methods.items()}


def _iterations(method: Method) -> int | None:
    return None if method.default_iterations is None else ITERATIONS.get(method.name, 3)


def _checked(name: str, phase: torch.Tensor, setup: OpticalSetup) -> torch.Tensor:
    """`phase` after asserting it is finite, float32, (H, W), in [-pi, pi) and reconstructs to finite values."""
    assert phase.shape == setup.shape and phase.dtype == torch.float32, name
    assert bool(torch.isfinite(phase).all()), name
    assert bool((phase >= -math.pi).all()) and bool((phase < math.pi).all()), name
    assert bool(torch.isfinite(setup.reconstruct(phase)).all()), name
    return phase


def roi_target(setup: OpticalSetup, value: float = 1.0) -> torch.Tensor:
    target = torch.zeros(setup.shape)
    rows, cols = setup.roi_slices
    target[rows, cols] = value
    return target


def test_every_registered_method_is_covered(methods: dict[str, Method]) -> None:
    kinds = {(m.needs_checkpoint, m.refines is not None) for m in METHODS.values()}
    assert kinds == {(False, False), (True, False), (True, True)}  # classical, learned, refined
    assert set(methods) == set(METHODS) and not any(m.needs_checkpoint for m in methods.values())


@pytest.mark.slow
def test_all_black_target_every_method(setup: OpticalSetup, methods: dict[str, Method]) -> None:
    run_every_method(methods, torch.zeros(setup.shape), setup)


@pytest.mark.slow
def test_all_white_target_every_method(setup: OpticalSetup, methods: dict[str, Method]) -> None:
    full = OpticalSetup(520e-9, 8e-6, 20e-3, setup.shape, setup.shape)
    run_every_method(methods, torch.ones(full.shape), full)
    run_every_method(methods, roi_target(setup), setup)


@pytest.mark.slow
def test_single_pixel_target_every_method(setup: OpticalSetup, methods: dict[str, Method]) -> None:
    target = torch.zeros(setup.shape)
    target[setup.shape[0] // 2, setup.shape[1] // 2] = 1.0
    run_every_method(methods, target, setup)


@pytest.mark.slow
def test_amplitudes_above_one(setup: OpticalSetup, methods: dict[str, Method]) -> None:
    generator = torch.Generator().manual_seed(0)
    target = roi_target(setup) * torch.rand(setup.shape, generator=generator)
    bright = run_every_method(methods, target * 1000.0, setup)
    torch.testing.assert_close(check_target(target * 1000.0, setup), check_target(target, setup))
    # Only the amplitude's shape matters: the phase is the same as for the target scaled to max 1.
    plain = run_every_method(methods, target / target.max(), setup)
    for name in methods:
        difference = torch.remainder(bright[name] - plain[name] + math.pi, 2 * math.pi) - math.pi
        assert float(difference.abs().max()) < 1e-3, name


def test_dpac_zero_amplitude(setup: OpticalSetup) -> None:
    # All black: the back-propagated field is zero, so every pixel encodes amplitude 0 at phase 0, i.e.
    # +-acos(0) = +-pi/2 on the checkerboard, whose neighbour pairs cancel exactly.
    phase = DPAC(torch.zeros(setup.shape), setup)
    rows = torch.arange(setup.shape[0])[:, None]
    cols = torch.arange(setup.shape[1])[None, :]
    expected = torch.where((rows + cols) % 2 == 0, math.pi / 2, -math.pi / 2).float()
    torch.testing.assert_close(phase, expected, atol=1e-6, rtol=0)
    # Partly black: zero-amplitude regions stay finite.
    target = roi_target(setup)
    target[:, : setup.shape[1] // 2] = 0.0
    assert bool(torch.isfinite(DPAC(target, setup)).all())


@pytest.mark.parametrize(("bad", "word"), [(float("nan"), "NaN"), (float("inf"), "inf"), (-float("inf"), "inf")])
def test_nan_or_inf_target_raises(setup: OpticalSetup, methods: dict[str, Method], bad: float, word: str) -> None:
    target = roi_target(setup)
    target[30, 30] = bad
    for method in methods.values():
        with pytest.raises(ValueError, match=rf"finite.* 1 {word}"):
            method(target, setup)
    with pytest.raises(ValueError, match="finite"):
        check_target(roi_target(setup).double() * 1e300, setup)  # overflows float32


def test_finite_gradients_at_zero_amplitude() -> None:
    # So far away that the band limit passes only the zero frequency, where exp(i phase) sums to exactly zero:
    # 0 on even (row + col) and +-pi (alternating by row) on odd pixels, so float32's sin(+-pi) = -+8.7e-8
    # cancel too. The reconstruction is then exactly zero everywhere, where a square-root amplitude has no
    # gradient.
    far = OpticalSetup(520e-9, 1e-6, 0.5, (64, 64), (32, 32))
    rows = torch.arange(64)[:, None]
    cols = torch.arange(64)[None, :]
    odd = torch.where(rows % 2 == 0, math.pi, -math.pi)
    phase = torch.where((rows + cols) % 2 == 0, 0.0, odd).float().requires_grad_()
    assert bool((far.reconstruct(phase.detach()) == 0).all()), "precondition: an exactly dark reconstruction"

    naive = far.target_propagator()(torch.polar(torch.ones_like(phase), phase))
    torch.sqrt(naive.real**2 + naive.imag**2).sum().backward()
    assert not bool(torch.isfinite(phase.grad).all()), "precondition: the square-root amplitude trap is reached"

    for target in (torch.zeros(64, 64), roi_target(far) * 0.5):
        phase.grad = None
        loss = roi_loss(phase, target, far)
        loss.backward()
        assert bool(torch.isfinite(loss)) and bool(torch.isfinite(phase.grad).all())
