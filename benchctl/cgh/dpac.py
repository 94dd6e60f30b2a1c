"""Double-phase amplitude coding (DPAC): a one-shot phase-only encoding of the target's field at the SLM (with a
fitted optical model, of the field that bench must be given: its wavefront removed, its beam divided out)."""

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


def _dpac(target: torch.Tensor, setup: OpticalSetup, _iterations: Optional[int], _seed: int,
          _progress: Optional[Progress]) -> torch.Tensor:
    with torch.no_grad():
        field = setup.slm_propagator()(target)
        if setup.field_model is not None:
            field = through_fitted_bench(field, setup.slm_factor().to(field.device))
        amplitude = field.abs()
        peak = amplitude.max()
        # An all-black target back-propagates to zero: divide by 1 there instead of by 0.
        normalised = amplitude / torch.where(peak > 0, peak, torch.ones_like(peak))
        phase = double_phase(normalised, field.angle())
        return phase - phase.mean()


DPAC = register(Method(
    name="dpac",
    description="Double-phase amplitude coding of the back-propagated target (one shot, no iterations)",
    default_iterations=None,
    algorithm=_dpac,
))
