"""Double-phase amplitude coding (DPAC): a one-shot phase-only encoding of the target's field at the SLM."""

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


def _dpac(target: torch.Tensor, setup: OpticalSetup, _iterations: Optional[int], _seed: int,
          _progress: Optional[Progress]) -> torch.Tensor:
    with torch.no_grad():
        field = setup.slm_propagator()(target)
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
