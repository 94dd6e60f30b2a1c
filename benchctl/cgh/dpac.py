"""Double-phase amplitude coding (DPAC): a one-shot phase-only encoding of the target's field at the SLM (with a
fitted optical model, of the field that bench must be given: its wavefront removed, its beam divided out, its
unmodulated zero order subtracted).

A scene with depth is coded as Tensor Holography's classical pipeline codes it (Shi et al. 2021): the scene's field
is built layer by layer with occlusion (`layered_field`), taken to the SLM, low-passed by a Gaussian (anti-aliased
DPAC: the checkerboard of the double phase then puts no copy of the field's high frequencies inside the iris), and
double-phase coded as above.
"""

from __future__ import annotations

import math
from typing import Optional

import torch

from benchctl.cgh.method import Method, Progress, register
from benchctl.optics.focal_stack import FocalStackTarget
from benchctl.optics.propagation import propagate
from benchctl.optics.setup import OpticalSetup

ANTI_ALIAS_SIGMA_PX = 0.7
"""Standard deviation (SLM pixels) of the Gaussian low-pass before a scene's double-phase coding (docs/depth.md
measures the choice)."""


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


def encode(field: torch.Tensor, setup: OpticalSetup) -> torch.Tensor:
    """The double-phase hologram of `field`, the wanted field leaving the SLM (through the fitted bench, if any)."""
    if setup.field_model is not None:
        field = through_fitted_bench(field, setup.slm_factor().to(field.device))
    peak = field.abs().max()
    # An all-black target back-propagates to zero: divide by 1 there instead of by 0.
    normalised = field / torch.where(peak > 0, peak, torch.ones_like(peak))
    if setup.field_model is not None:
        normalised = without_zero_order(normalised, setup.field_model.zero_order)
    phase = double_phase(normalised.abs(), normalised.angle())
    return phase - phase.mean()


def _dpac(target: torch.Tensor, setup: OpticalSetup, _iterations: Optional[int], _seed: int,
          _progress: Optional[Progress]) -> torch.Tensor:
    with torch.no_grad():
        return encode(setup.slm_propagator()(target), setup)


def layered_field(target: FocalStackTarget, setup: OpticalSetup, at_m: float) -> torch.Tensor:
    """The field of a scene with depth at `at_m` from the SLM, layer by layer with occlusion (complex64 (H, W)).

    Each plane's layer is the amplitude where that plane is in focus, with a flat phase. From the layer nearest
    the SLM outwards, the field so far is propagated to the next layer, blocked where that layer is (its
    silhouette: the camera looks from beyond the planes towards the SLM, so farther layers hide nearer ones), and
    the layer's own light is added; the field at the last layer is then propagated to `at_m` (0: the SLM; the
    middle of the planes: Tensor Holography's mid-plane hologram). No iris: this is the scene, not the bench.
    """
    owner = target.masks.argmax(dim=0)
    field = torch.zeros(target.amplitude.shape, dtype=torch.complex64, device=target.amplitude.device)
    previous = target.planes_m[0]
    for k, plane in enumerate(target.planes_m):
        if plane != previous:
            field = propagate(field, plane - previous, setup.wavelength_m, setup.pitch_m, padding=setup.padding)
        layer = owner == k
        field = torch.where(layer, target.amplitude.to(field.dtype), field)
        previous = plane
    return propagate(field, at_m - previous, setup.wavelength_m, setup.pitch_m, padding=setup.padding)


def anti_aliased(field: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """`field` blurred by a Gaussian of `sigma_px` SLM pixels (applied as its transfer function on the FFT grid)."""
    if sigma_px == 0:
        return field
    fy = torch.fft.fftfreq(field.shape[-2], dtype=torch.float64, device=field.device)[:, None]
    fx = torch.fft.fftfreq(field.shape[-1], dtype=torch.float64, device=field.device)[None, :]
    gain = torch.exp(-2 * math.pi**2 * sigma_px**2 * (fy.square() + fx.square())).to(field.real.dtype)
    return torch.fft.ifft2(torch.fft.fft2(field) * gain)


def _layered_dpac(target: FocalStackTarget, setup: OpticalSetup, _iterations: Optional[int], _seed: int,
                  _progress: Optional[Progress]) -> torch.Tensor:
    with torch.no_grad():
        return encode(anti_aliased(layered_field(target, setup, 0.0), ANTI_ALIAS_SIGMA_PX), setup)


DPAC = register(Method(
    name="dpac",
    description="Double-phase amplitude coding of the back-propagated target (one shot, no iterations); a scene with "
                "depth: of its layered field, anti-aliased",
    default_iterations=None,
    algorithm=_dpac,
    focal_stack=_layered_dpac,
))
