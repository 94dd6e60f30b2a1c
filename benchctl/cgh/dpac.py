"""Double-phase amplitude coding (DPAC): a one-shot phase-only encoding of the target's field at the SLM (with a
fitted optical model, of the field that bench must be given: its wavefront removed, its beam divided out, its
unmodulated zero order subtracted)."""

from __future__ import annotations

from typing import Optional

import torch

from benchctl.cgh.method import Method, Progress, register
from benchctl.optics.setup import OpticalSetup


def double_phase(amplitude: torch.Tensor, phase: torch.Tensor) -> torch.Tensor:
    """Encode a field amplitude * exp(i phase), amplitude in [0, 1], as one phase per pixel.

    Pixels where row + col is even get phase + acos(amplitude), the others phase - acos(amplitude). Because
    exp(i(p + acos a)) + exp(i(p - acos a)) = 2 a exp(i p), averaging neighbours (the low-pass of the bench's
    Fourier-plane iris) gives the field back; the rest goes to the highest spatial frequency.
    """
    offset = torch.acos(amplitude.clamp(0.0, 1.0))
    h, w = amplitude.shape[-2:]
    rows = torch.arange(h, device=amplitude.device)[:, None]
    cols = torch.arange(w, device=amplitude.device)[None, :]
    return phase + torch.where((rows + cols) % 2 == 0, offset, -offset)


BEAM_FLOOR = 0.1
"""With a fitted beam, its amplitude is divided out no lower than this fraction of its peak: a dim beam edge
would otherwise ask for more light than the SLM has and darken the whole hologram after normalisation."""


def through_fitted_bench(field: torch.Tensor, factor: torch.Tensor) -> torch.Tensor:
    """The SLM field that a bench lighting the SLM with `factor` = A e^(i W) (the fitted beam and wavefront error)
    turns into `field`: field e^(-i W) / A, A floored at BEAM_FLOOR of its peak."""
    amplitude = factor.abs()
    return field * torch.exp(-1j * factor.angle()) / torch.clamp(amplitude, min=BEAM_FLOOR * float(amplitude.max()))


def without_zero_order(field: torch.Tensor, fraction: float) -> torch.Tensor:
    """The field e, |e| <= 1, to encode so that a panel leaving `fraction` f of the light unmodulated shows
    (1 - f) e + f = s * field, with the largest s for which every pixel stays within reach: `field` normalised to
    a peak of 1, s is the smallest positive root over the pixels of |s field - f| = 1 - f."""
    if not fraction:
        return field
    f = float(fraction)
    power, real = field.abs().square(), field.real
    lit = power > 0
    roots = (f * real + torch.sqrt(f * f * real.square() + power * (1 - 2 * f))) / torch.where(lit, power, 1.0)
    scale = roots[lit].min() if bool(lit.any()) else roots.new_tensor(1.0)
    return (scale * field - f) / (1 - f)


def _dpac(target: torch.Tensor, setup: OpticalSetup, _iterations: Optional[int], _seed: int,
          _progress: Optional[Progress]) -> torch.Tensor:
    with torch.no_grad():
        field = setup.slm_propagator()(target)
        if setup.field_model is not None:
            field = through_fitted_bench(field, setup.slm_factor().to(field.device))
        peak = field.abs().max()
        # An all-black target back-propagates to zero: divide by 1 there instead of by 0.
        normalised = field / torch.where(peak > 0, peak, torch.ones_like(peak))
        if setup.field_model is not None:
            normalised = without_zero_order(normalised, setup.field_model.zero_order)
        phase = double_phase(normalised.abs(), normalised.angle())
        return phase - phase.mean()


DPAC = register(Method(
    name="dpac",
    description="Double-phase amplitude coding of the back-propagated target (one shot, no iterations)",
    default_iterations=None,
    algorithm=_dpac,
))
