"""Gerchberg-Saxton: alternate between the SLM plane (unit amplitude) and the target plane (target amplitude).

Choices (documented because they change results):
- Only the ROI is constrained. Outside it the propagated field is kept as it is, a "don't care" region where
  the algorithm may put the light it cannot use (forcing it dark gave 15-25 % higher ROI error at 50
  iterations on the test targets).
- Inside the ROI the amplitude becomes s * target with the energy-preserving s = sqrt(sum |u|^2 / sum t^2)
  over the ROI: the constraint reshapes the light already in the ROI without adding or removing any, so
  the brightness does not drift between iterations.
- The start is the target with a uniformly random phase in [0, 2 pi) (seeded), the usual diffuser start: it
  spreads the back-propagated light over the whole SLM instead of a few low frequencies.
- 50 iterations by default: on a 96 x 128 test grid the ROI error falls ~70 % in the first 50 iterations and
  only 3-7 % more in the next 50 (0.1-0.3 % per iteration at 50). It stops earlier once the ROI error (after
  a least-squares scale) stopped improving, by SGD's rule (`stopped_improving`, same tolerance).
- With a fitted optical model (model calibration), the SLM field is the model's going forward (beam, wavefront
  error, crosstalk, zero order); coming back, the zero order's share of the field is subtracted and the
  wavefront removed.
- Tried on the Fresnel-scaled simulated bench and not kept (worse or no better at 10-200 iterations,
  chart:siemens and photo:coffee): the DPAC hologram as the start, the whole target plane constrained,
  mixed-region amplitude freedom (MRAF, m = 0.6 / 0.8), weighted GS, and double-phase encoding in place of
  the SLM amplitude constraint.
"""

from __future__ import annotations

import math
from typing import Optional

import torch

from benchctl.cgh.method import TOLERANCE, Method, Progress, register, stopped_improving
from benchctl.optics.metrics import lsq_scale
from benchctl.optics.setup import OpticalSetup

DEFAULT_ITERATIONS = 50


def _gerchberg_saxton(target: torch.Tensor, setup: OpticalSetup, iterations: Optional[int], seed: int,
                      progress: Optional[Progress]) -> torch.Tensor:
    assert iterations is not None  # Method resolves the default for iterative methods
    to_slm, to_target = setup.slm_propagator(), setup.target_propagator()
    rows, cols = setup.roi_slices
    target_roi = target[rows, cols]
    target_energy = target_roi.square().sum()
    # With an all-black target any s gives a zero ROI; divide by 1 instead of 0 so s stays finite.
    target_energy = torch.where(target_energy > 0, target_energy, torch.ones_like(target_energy))
    generator = torch.Generator(device=target.device).manual_seed(seed)
    start = torch.rand(target.shape, generator=generator, device=target.device) * (2.0 * math.pi)
    errors: list[float] = []
    # A fitted bench shows A e^(i W) ((1 - f) e^(i phase) + f): back from it, the zero order f A e^(i W) is
    # subtracted and the phase W removed (the phase-only projection; A > 0 does not change the angle). The
    # diffuser start has no scale to subtract f at.
    model = setup.field_model
    factor: torch.Tensor | None = None
    unmodulated: torch.Tensor | None = None
    if model is not None:
        factor = setup.slm_factor().to(target.device)
        unmodulated = factor * model.zero_order if model.zero_order else None
    with torch.no_grad():
        phase = _slm_phase(to_slm(torch.polar(target, start)), factor)
        for done in range(1, iterations + 1):
            field = to_target(setup.slm_field(phase))
            roi = field[rows, cols]
            amplitude = roi.abs()
            errors.append(float((lsq_scale(amplitude, target_roi) * amplitude - target_roi).square().mean()))
            if stopped_improving(errors, TOLERANCE):
                if progress is not None:
                    progress(done - 1, done - 1)
                break
            scale = torch.sqrt(amplitude.square().sum() / target_energy)
            field[rows, cols] = torch.polar(scale * target_roi, roi.angle())
            back = to_slm(field)
            phase = _slm_phase(back if unmodulated is None else back - unmodulated, factor)
            if progress is not None:
                progress(done, iterations)
    return phase


def _slm_phase(field: torch.Tensor, factor: torch.Tensor | None) -> torch.Tensor:
    return field.angle() if factor is None else (field * factor.conj()).angle()


GERCHBERG_SAXTON = register(Method(
    name="gs",
    description="Gerchberg-Saxton with the ROI constrained and the rest of the target plane left free",
    default_iterations=DEFAULT_ITERATIONS,
    algorithm=_gerchberg_saxton,
))
