"""What makes a real bench differ from the ideal model: Zernike wavefront error at the SLM, a Gaussian beam,
SLM pixel crosstalk. The simulated bench renders with these; a fitted optical model (optics.fitted) uses the
same functions, differentiably, so the one definition serves both the hidden truth and its estimate.

Zernike convention: ANSI Z80.28 / OSA (Thibos et al. 2002), RMS-normalised, so a coefficient of c waves is an
RMS wavefront error of c waves over the unit disc: Z_n^m = N R_n^|m|(rho) cos(m theta) (m >= 0) or
N R_n^|m|(rho) sin(|m| theta) (m < 0), N = sqrt((2 - delta_m0)(n + 1)). The unit disc is the circle that
circumscribes the SLM panel (radius half its diagonal), centred on the panel; x runs along columns (right),
y along rows (down), theta from +x towards +y.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch

# Term name -> (n, m), in ANSI order. Tilt moves the image by distance x tan(angle), angle = 2 c lambda / R for c
# waves over the pupil radius R: a registration made on the same bench absorbs it, one made elsewhere does not.
ZERNIKE_TERMS: dict[str, tuple[int, int]] = {
    "tilt_vertical": (1, -1),
    "tilt_horizontal": (1, 1),
    "astigmatism_oblique": (2, -2),
    "defocus": (2, 0),
    "astigmatism_vertical": (2, 2),
    "coma_vertical": (3, -1),
    "coma_horizontal": (3, 1),
    "spherical": (4, 0),
}


Pitch = float | Sequence[float]


def _pair(pitch_m: Pitch) -> tuple[float, float]:
    return (float(pitch_m), float(pitch_m)) if isinstance(pitch_m, (int, float)) else (pitch_m[0], pitch_m[1])


def _radial(n: int, m: int, rho: torch.Tensor) -> torch.Tensor:
    """The Zernike radial polynomial R_n^m(rho), m >= 0."""
    out = torch.zeros_like(rho)
    for k in range((n - m) // 2 + 1):
        coefficient = (-1) ** k * math.factorial(n - k) / (
            math.factorial(k) * math.factorial((n + m) // 2 - k) * math.factorial((n - m) // 2 - k))
        out = out + coefficient * rho ** (n - 2 * k)
    return out


def pupil_coordinates(shape: tuple[int, int], pitch_m: Pitch) -> tuple[torch.Tensor, torch.Tensor]:
    """(y, x) in metres of every pixel centre from the panel's centre, float64, shaped (H, 1) and (1, W)."""
    h, w = shape
    pitch_m = _pair(pitch_m)
    y = (torch.arange(h, dtype=torch.float64) - (h - 1) / 2) * pitch_m[0]
    x = (torch.arange(w, dtype=torch.float64) - (w - 1) / 2) * pitch_m[1]
    return y[:, None], x[None, :]


def pupil_radius_m(shape: tuple[int, int], pitch_m: Pitch) -> float:
    """Radius of the unit disc of the Zernike terms: half the panel's diagonal."""
    pitch_m = _pair(pitch_m)
    return math.hypot(shape[0] * pitch_m[0], shape[1] * pitch_m[1]) / 2


def zernike_basis(shape: tuple[int, int], pitch_m: Pitch,
                  names: Sequence[str] = tuple(ZERNIKE_TERMS)) -> torch.Tensor:
    """The RMS-normalised terms `names` over the panel, (len(names), H, W) float64."""
    y, x = pupil_coordinates(shape, pitch_m)
    radius = pupil_radius_m(shape, pitch_m)
    rho = torch.sqrt(y.square() + x.square()) / radius
    theta = torch.atan2(y.expand(shape), x.expand(shape))
    terms = []
    for name in names:
        if name not in ZERNIKE_TERMS:
            raise ValueError(f"unknown Zernike term {name!r} (known: {', '.join(ZERNIKE_TERMS)})")
        n, m = ZERNIKE_TERMS[name]
        norm = math.sqrt((2 - (m == 0)) * (n + 1))
        angular = torch.cos(m * theta) if m >= 0 else torch.sin(-m * theta)
        terms.append(norm * _radial(n, abs(m), rho) * angular)
    return torch.stack(terms)


def wavefront_phase(shape: tuple[int, int], pitch_m: Pitch, waves: Mapping[str, float]) -> torch.Tensor:
    """Phase (rad, (H, W) float64) of the wavefront error sum_j c_j Z_j, coefficients in waves by term name."""
    if not waves:
        return torch.zeros(shape, dtype=torch.float64)
    names = list(waves)
    coefficients = torch.tensor([float(waves[name]) for name in names], dtype=torch.float64)
    return 2 * math.pi * torch.einsum("k,khw->hw", coefficients, zernike_basis(shape, pitch_m, names))


def defocus_focal_length_m(waves: float, wavelength_m: float, shape: tuple[int, int],
                           pitch_m: Pitch) -> float:
    """Focal length of the thin lens equal to `waves` of defocus: Z_2^0 = sqrt(3) (2 rho^2 - 1) adds the phase
    2 pi c 2 sqrt(3) r^2 / R^2, a lens exp(-i pi r^2 / (lambda f)) with f = -R^2 / (4 sqrt(3) c lambda)
    (positive c diverges)."""
    return -pupil_radius_m(shape, pitch_m) ** 2 / (4 * math.sqrt(3) * waves * wavelength_m)


def gaussian_beam_power(shape: tuple[int, int], pitch_m: Pitch, waist_m: torch.Tensor | float,
                        offset_m: torch.Tensor | Sequence[float] = (0.0, 0.0)) -> torch.Tensor:
    """Fraction of a Gaussian beam's power on each pixel (H, W): 2 / (pi w^2) exp(-2 r^2 / w^2) pitch^2 with r
    measured from `offset_m` (y, x) off the panel's centre; w the 1/e^2 intensity radius. Differentiable in
    waist and offset; light that misses the panel is lost."""
    y, x = pupil_coordinates(shape, pitch_m)
    waist = torch.as_tensor(waist_m, dtype=torch.float64)
    offset = torch.as_tensor(offset_m, dtype=torch.float64)
    r2 = (y - offset[0]).square() + (x - offset[1]).square()
    return 2 / (math.pi * waist.square()) * torch.exp(-2 * r2 / waist.square()) * math.prod(_pair(pitch_m))


def tilt_phase(shape: tuple[int, int], pitch_m: Pitch, tilt_rad: Sequence[float],
               wavelength_m: float) -> torch.Tensor:
    """Phase (H, W) float64 of a plane wave arriving tilted by (theta_y, theta_x): 2 pi (y sin theta_y +
    x sin theta_x) / lambda. At the target plane z downstream the image moves by z tan(theta) along each axis."""
    y, x = pupil_coordinates(shape, pitch_m)
    return 2 * math.pi * (y * math.sin(tilt_rad[0]) + x * math.sin(tilt_rad[1])) / wavelength_m


def crosstalk_blur(phase: torch.Tensor, sigma_px: torch.Tensor | float) -> torch.Tensor:
    """SLM pixel crosstalk (fringing fields): the phase the panel drives, blurred by a Gaussian of `sigma_px`
    pixels before it modulates the light (`gaussian_blur` with variance sigma^2)."""
    return gaussian_blur(phase, torch.as_tensor(sigma_px, dtype=torch.float64).square())


def gaussian_blur(images: torch.Tensor, variance_px2: torch.Tensor | float) -> torch.Tensor:
    """(..., H, W) blurred by a Gaussian of `variance_px2` square pixels, computed in the input's precision (float32
    or float64, other dtypes in float64) and returned in its dtype; unchanged at 0. Applied in frequency (exactly
    exp(-2 pi^2 variance f^2) at f cycles per pixel), periodic at the edges, where the error is confined to about
    one blur width. Differentiable in the variance, also at 0."""
    variance = torch.as_tensor(variance_px2, dtype=torch.float64)
    if not variance.requires_grad and float(variance) == 0:
        return images
    real = images.dtype if images.dtype in (torch.float32, torch.float64) else torch.float64
    h, w = images.shape[-2:]
    fy = torch.fft.fftfreq(h, dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(w, dtype=torch.float64)[None, :]
    response = torch.exp(-2 * math.pi**2 * variance * (fy.square() + fx.square())).to(images.device, real)
    spectrum = torch.fft.rfft2(images.to(real)) * response
    return torch.fft.irfft2(spectrum, s=(h, w)).to(images.dtype)
