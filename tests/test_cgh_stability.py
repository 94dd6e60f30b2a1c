"""Hologram methods, classical and learned, on degenerate inputs: black, white, single-pixel, large and non-finite
targets, zero amplitude."""

from __future__ import annotations

import math

import pytest
import torch

from benchctl.cgh import DPAC, METHODS, Method, OpticalSetup, check_target, roi_loss, sgd_method
from benchctl.cgh.learned import LEARNED_METHODS, Checkpoint, build_model, learned_method
from benchctl.cgh.learned.geometry import geometry_of

ITERATIONS = {"dpac": None, "gs": 10, "sgd": 10}


@pytest.fixture(scope="module")
def setup() -> OpticalSetup:
    return OpticalSetup(wavelength_m=520e-9, pitch_m=8e-6, distance_m=20e-3, shape=(64, 64), roi=(48, 48))


def run_every_method(target: torch.Tensor, setup: OpticalSetup) -> dict[str, torch.Tensor]:
    """Each method's phase for `target`, checked to be finite, float32, (H, W) and in [-pi, pi)."""
    return {name: _checked(name, method(target, setup, iterations=ITERATIONS.get(name)), setup)
            for name, method in METHODS.items()}


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


def test_all_black_target_every_method(setup: OpticalSetup) -> None:
    run_every_method(torch.zeros(setup.shape), setup)


def test_all_white_target_every_method(setup: OpticalSetup) -> None:
    full = OpticalSetup(520e-9, 8e-6, 20e-3, setup.shape, setup.shape)
    run_every_method(torch.ones(full.shape), full)
    run_every_method(roi_target(setup), setup)


def test_single_pixel_target_every_method(setup: OpticalSetup) -> None:
    target = torch.zeros(setup.shape)
    target[setup.shape[0] // 2, setup.shape[1] // 2] = 1.0
    run_every_method(target, setup)


def test_amplitudes_above_one(setup: OpticalSetup) -> None:
    generator = torch.Generator().manual_seed(0)
    target = roi_target(setup) * torch.rand(setup.shape, generator=generator)
    bright = run_every_method(target * 1000.0, setup)
    torch.testing.assert_close(check_target(target * 1000.0, setup), check_target(target, setup))
    # Only the amplitude's shape matters: the phase is the same as for the target scaled to max 1.
    plain = run_every_method(target / target.max(), setup)
    for name in METHODS:
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
def test_nan_or_inf_target_raises(setup: OpticalSetup, bad: float, word: str) -> None:
    target = roi_target(setup)
    target[30, 30] = bad
    for method in METHODS.values():
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


# --- learned methods ------------------------------------------------------------------------------------------
# No shipped checkpoint fits this 64 x 64 grid, so each learned method gets an untrained one (seeded weights):
# stability does not depend on training. "+sgd" refines the network's hologram (at 3 iterations here).


@pytest.fixture(scope="module")
def learned(setup: OpticalSetup, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Method]:
    """Every learned method, and ccnn-dcm4 refined by SGD, with an untrained checkpoint for `setup`."""
    folder = tmp_path_factory.mktemp("untrained")
    methods: dict[str, Method] = {}
    for name in LEARNED_METHODS:
        torch.manual_seed(0)
        model = build_model(name, setup).eval()
        path = Checkpoint(method=name, geometry={"green": geometry_of(setup)},
                          weights={"green": model.state_dict()}).save(folder / f"{name}.pt")
        methods[name] = learned_method(name, path)
    methods["ccnn-dcm4+sgd"] = sgd_method("ccnn-dcm4+sgd", init=methods["ccnn-dcm4"])
    return methods


def run_learned(methods: dict[str, Method], target: torch.Tensor, setup: OpticalSetup) -> dict[str, torch.Tensor]:
    """Each learned method's phase for `target`, checked like `run_every_method` checks the classical ones."""
    return {name: _checked(name, method(target, setup, iterations=3 if method.default_iterations else None), setup)
            for name, method in methods.items()}


def test_learned_all_black_and_single_pixel(setup: OpticalSetup, learned: dict[str, Method]) -> None:
    run_learned(learned, torch.zeros(setup.shape), setup)
    target = torch.zeros(setup.shape)
    target[setup.shape[0] // 2, setup.shape[1] // 2] = 1.0
    run_learned(learned, target, setup)


def test_learned_amplitudes_above_one(setup: OpticalSetup, learned: dict[str, Method]) -> None:
    generator = torch.Generator().manual_seed(0)
    target = roi_target(setup) * torch.rand(setup.shape, generator=generator)
    bright = run_learned(learned, target * 1000.0, setup)
    plain = run_learned(learned, target / target.max(), setup)
    for name in learned:  # the network sees the target scaled to max 1 either way
        difference = torch.remainder(bright[name] - plain[name] + math.pi, 2 * math.pi) - math.pi
        assert float(difference.abs().max()) < 1e-3, name


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_learned_nan_or_inf_target_refused(setup: OpticalSetup, learned: dict[str, Method], bad: float) -> None:
    target = roi_target(setup)
    target[30, 30] = bad
    for method in learned.values():
        with pytest.raises(ValueError, match="finite"):
            method(target, setup)
