"""Band-limited angular-spectrum propagation (Matsushima & Shimobaba 2009) with geometry-aware padding.

Conventions: fields are complex tensors shaped (..., H, W); +z propagates SLM -> target plane, -z back.
The transfer function is built in float64 on the exact FFT frequency grid with the constant k z piston
removed, then cast to the field's precision; evanescent components are zeroed, so no NaN can appear.

Padding. The discrete transfer function makes a circular convolution over the padded grid, so light that
leaves the grid on one side comes back on the other unless a guard band of zeros absorbs it. Light from the
grid travels sideways by at most K = |z| tan(theta) pixels, theta the steepest angle the grid carries
(sin theta = lambda / 2 pitch per axis); the Matsushima band limit cuts every ray that would travel further
than half the padded grid, so a guard band as wide as the grid always absorbs the geometric light. What
no finite guard band absorbs are the edge-diffraction tails of the hard spectral edge, which fall off only
as 1 / distance just beyond K. "auto" pads each axis by min(K, N) plus the margin that keeps the modelled
wrapped tails within AUTO_TOLERANCE (see `wrapped_tail_power`), at most N, then rounds up to a fast FFT
size; "2x" pads every axis by N, "<k>x" by (k - 1) N, an int by that many pixels on each side, and "none"
wraps all light that leaves. docs/propagation.md has the measurements behind the rule.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from numbers import Integral
from typing import Union

import torch

Padding = Union[str, int]
PADDING_MODES = ("auto", "2x", "none")


@dataclass(frozen=True)
class PropagationPlan:
    """What one propagation will compute: grid sizes, padding and how much of the spectrum is kept."""

    shape: tuple[int, int]
    padded_shape: tuple[int, int]
    pad: tuple[int, int, int, int]  # zeros added at top, bottom, left, right
    distance_m: float
    wavelength_m: float
    pitch_m: tuple[float, float]  # (dy, dx)
    padding: Padding
    band_limit: bool
    spread_px: tuple[float, float]  # K per axis in pixels (inf where the grid carries grazing light)
    passed_fraction: tuple[float, float]  # fraction of each axis' frequencies kept by the band limit
    aperture: float | None = None  # Fourier-plane iris radius as a fraction of the grid's Nyquist frequency

    @property
    def spread_fraction(self) -> tuple[float, float]:
        """K / N per axis: where it is well under 1/2, "auto" pads much less than "2x"."""
        return self.spread_px[0] / self.shape[0], self.spread_px[1] / self.shape[1]

    def describe(self) -> str:
        """One line a user can read: grid, padded grid, spread and band-limit figures."""
        (h, w), (ph, pw) = self.shape, self.padded_shape
        ky, kx = self.spread_px
        ry, rx = self.spread_fraction
        fy, fx = self.passed_fraction
        return (
            f"{h}x{w} -> {ph}x{pw} (padding={self.padding!s}, guard {ph - h}+{pw - w} px), "
            f"z={self.distance_m * 1e3:g} mm, lambda={self.wavelength_m * 1e9:g} nm, "
            f"spread K={ky:.0f}/{kx:.0f} px (K/N {ry:.2f}/{rx:.2f}), band limit keeps {fy:.2f} x {fx:.2f}"
            + (f", iris {self.aperture:g} x Nyquist" if self.aperture is not None else "")
        )


def _pair(value: float | tuple[float, float] | list[float]) -> tuple[float, float]:
    if isinstance(value, (tuple, list)):
        if len(value) != 2:
            raise ValueError(f"pitch_m must be a float or (dy, dx), got {value!r}")
        return float(value[0]), float(value[1])
    return float(value), float(value)


def reach_pixels(distance_m: float, wavelength_m: float,
                 pitch_m: float | tuple[float, float]) -> tuple[float, float]:
    """K per axis: the furthest any propagating plane wave of the grid moves sideways over |z|, in pixels.

    A plane wave (fy, fx) moves by lambda |z| f / sqrt(1 - lambda^2 (fy^2 + fx^2)) along each axis; the largest
    move is at the corner of the spectrum (both frequencies at Nyquist, 1 / (2 pitch)). Where that corner is
    evanescent the grid carries grazing light and K is infinite.
    """
    dy, dx = _pair(pitch_m)
    sy, sx = wavelength_m / (2.0 * dy), wavelength_m / (2.0 * dx)
    if distance_m == 0:
        return 0.0, 0.0
    cos_theta2 = 1.0 - sy * sy - sx * sx
    if cos_theta2 <= 0:
        return float("inf"), float("inf")
    scale = abs(distance_m) / math.sqrt(cos_theta2)
    return scale * sy / dy, scale * sx / dx


AUTO_TOLERANCE = 3.5e-3
"""Relative L2 error that "auto" allows the wrapped tails of a full-band field (both axes together, modelled).

Chosen by measurement (docs/propagation.md): at the paper geometry (3.74 um, 70 mm, 1088 x 1920 and
2160 x 3840, 680 / 520 / 450 nm) the ROI error of "auto" stays within 1.53x that of "2x" (goal: 2x), and
at 2160 x 3840 it pads 66-82 % of the 2x area. The measured ROI error is about 1.5x the modelled figure.
"""


def wrapped_tail_power(n: int, reach: float, guard: int) -> float:
    """Mean power per pixel that a guard band of `guard` zeros lets wrap around an axis of `n` pixels.

    The model: a full-band, unit-power, random-phase field (what a phase SLM shows). Its transfer function
    ends on a hard edge at +-Nyquist (or at the band limit, which moves the reach to half the padded extent),
    so beyond the reach K the impulse response is the two edges' diffraction tails,
    |1 / (d - K) - 1 / (d + K)| / (2 pi) at a distance d: slow (1 / (d - K)) just past K, 2 K / d^2 far out.
    Light from b pixels inside one edge lands a pixels inside the other after d = guard + 1 + a + b; the
    powers of all such pairs add (random phase), averaged over the axis and counted for both edges.
    """
    u = torch.arange(2 * n - 1, dtype=torch.float64)
    pairs = torch.minimum(u + 1, 2 * n - 1 - u)  # how many (a, b) have a + b = u
    d = guard + 1 + u
    k = min(reach, (n + guard) / 2)
    tail = (1 / (d - k) - 1 / (d + k)) / (2 * math.pi)
    return float(2 * (pairs * tail.square()).sum() / n)


def _auto_guard(n: int, reach: float) -> int:
    """The smallest guard band >= min(K, n) whose wrapped tails stay within AUTO_TOLERANCE; at most n.

    Where even n zeros cannot meet the tolerance (small grids, K close to or beyond N), "auto" pads what
    "2x" pads instead of growing past it.
    """
    budget = AUTO_TOLERANCE**2 / 2  # half for each axis
    low, high = math.ceil(min(reach, n)), n
    if low >= high or wrapped_tail_power(n, reach, low) <= budget:
        return min(low, high)
    if wrapped_tail_power(n, reach, high) > budget:
        return high
    while high - low > 1:  # invariant: low is too small, high is enough
        mid = (low + high) // 2
        if wrapped_tail_power(n, reach, mid) <= budget:
            high = mid
        else:
            low = mid
    return high


def _fft_size(n: int) -> int:
    """Smallest multiple of 4 >= n whose prime factors are all 2, 3, 5 or 7: fast for pocketfft and cuFFT.

    (Sizes with a single factor 2, like 6250, measured up to 30 % slower than their neighbours on a CPU.)
    """
    m = max(4, n + (-n) % 4)
    while True:
        k = m
        for p in (2, 3, 5, 7):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 4


def _guard(padding: Padding, n: int, reach: float) -> int:
    """Zeros to add along one axis of n samples (both sides together)."""
    if isinstance(padding, Integral) and not isinstance(padding, bool):
        if padding < 0:
            raise ValueError(f"padding must be >= 0 pixels per side, got {padding}")
        return 2 * int(padding)
    if padding == "none":
        return 0
    if isinstance(padding, str) and padding.endswith("x") and padding[:-1].isdigit() and int(padding[:-1]) >= 1:
        return (int(padding[:-1]) - 1) * n
    if padding == "auto":
        if reach == 0:
            return 0
        return _fft_size(n + _auto_guard(n, reach)) - n
    raise ValueError(f"padding must be one of {PADDING_MODES}, '<k>x' or an int (pixels per side), got {padding!r}")


def _band_limit(m: int, pitch: float, distance_m: float, wavelength_m: float) -> float:
    """Matsushima's per-axis frequency limit for a padded extent of m samples."""
    df = 1.0 / (m * pitch)
    return 1.0 / (wavelength_m * math.sqrt((2.0 * df * distance_m) ** 2 + 1.0))


def plan_propagation(
    shape: tuple[int, int],
    distance_m: float,
    wavelength_m: float,
    pitch_m: float | tuple[float, float],
    *,
    padding: Padding = "auto",
    band_limit: bool = True,
    aperture: float | None = None,
) -> PropagationPlan:
    """Decide padded grid and band limit for a field of `shape` (H, W) without computing anything big."""
    if len(shape) != 2:
        raise ValueError(f"shape must be (H, W), got {shape!r}")
    h, w = int(shape[0]), int(shape[1])
    if h < 1 or w < 1:
        raise ValueError(f"field shape must be at least 1x1, got {shape}")
    if not (wavelength_m > 0 and math.isfinite(wavelength_m)):
        raise ValueError(f"wavelength_m must be positive, got {wavelength_m}")
    if not math.isfinite(distance_m):
        raise ValueError(f"distance_m must be finite, got {distance_m}")
    dy, dx = _pair(pitch_m)
    if not (dy > 0 and dx > 0 and math.isfinite(dy) and math.isfinite(dx)):
        raise ValueError(f"pitch_m must be positive, got {pitch_m}")
    if aperture is not None and not (0 < aperture and math.isfinite(aperture)):
        raise ValueError(f"aperture must be a positive fraction of the Nyquist frequency, got {aperture}")
    ky, kx = reach_pixels(distance_m, wavelength_m, (dy, dx))
    gy, gx = _guard(padding, h, ky), _guard(padding, w, kx)
    ph, pw = h + gy, w + gx
    fractions = []
    for m, d in ((ph, dy), (pw, dx)):
        freqs = torch.fft.fftfreq(m, d=d, dtype=torch.float64).abs()
        keep = freqs < 1.0 / wavelength_m
        if band_limit and distance_m != 0:
            keep &= freqs < _band_limit(m, d, distance_m, wavelength_m)
        fractions.append(float(keep.double().mean()))
    return PropagationPlan(
        shape=(h, w),
        padded_shape=(ph, pw),
        # All zeros after the field: a circular convolution does not care where the guard band sits.
        pad=(0, gy, 0, gx),
        distance_m=float(distance_m),
        wavelength_m=float(wavelength_m),
        pitch_m=(dy, dx),
        padding=padding,
        band_limit=band_limit,
        spread_px=(ky, kx),
        passed_fraction=(fractions[0], fractions[1]),
        aperture=None if aperture is None else float(aperture),
    )


def transfer_function(plan: PropagationPlan, dtype: torch.dtype = torch.complex64,
                      device: torch.device | str | None = None) -> torch.Tensor:
    """The band-limited ASM transfer function on the padded FFT grid (unshifted), as complex `dtype`.

    With `plan.aperture` it also holds the Fourier-plane iris of a 4f relay between SLM and propagation.

    exp(i 2 pi z (sqrt(1/lambda^2 - f^2) - 1/lambda)): the piston k z is left out (it only sets a global
    phase) so that the float64 phase stays small enough to survive the cast to complex64.
    """
    (m_y, m_x), (dy, dx) = plan.padded_shape, plan.pitch_m
    z, lam = plan.distance_m, plan.wavelength_m
    fy = torch.fft.fftfreq(m_y, d=dy, dtype=torch.float64, device=device)
    fx = torch.fft.fftfreq(m_x, d=dx, dtype=torch.float64, device=device)
    keep_y, keep_x = torch.ones_like(fy, dtype=torch.bool), torch.ones_like(fx, dtype=torch.bool)
    if plan.band_limit and z != 0:
        keep_y = fy.abs() < _band_limit(m_y, dy, z, lam)
        keep_x = fx.abs() < _band_limit(m_x, dx, z, lam)
    f2 = fy[:, None].square() + fx[None, :].square()
    keep = (f2 < 1.0 / lam**2) & keep_y[:, None] & keep_x[None, :]
    if plan.aperture is not None:
        # The iris in the Fourier plane of the relay: a disc in frequency, radius given in Nyquist units.
        keep &= (2 * dy * fy[:, None]).square() + (2 * dx * fx[None, :]).square() < plan.aperture**2
    # 2 pi z (sqrt(1/lam^2 - f^2) - 1/lam) rewritten as -2 pi z f^2 / (sqrt(1/lam^2 - f^2) + 1/lam): no
    # cancellation of two ~1e6 rad terms, and finite (then masked) where the root's argument is negative.
    root = f2.neg().add_(1.0 / lam**2).clamp_min_(0.0).sqrt_().add_(1.0 / lam)
    phase = f2.mul_(-2.0 * math.pi * z).div_(root)
    del root
    real_dtype = torch.float64 if dtype == torch.complex128 else torch.float32
    h = torch.complex(torch.cos(phase).to(real_dtype), torch.sin(phase).to(real_dtype))
    return h.mul_(keep).to(dtype)


def _check_shape(field: torch.Tensor) -> None:
    if not isinstance(field, torch.Tensor):
        raise TypeError(f"field must be a torch.Tensor, got {type(field).__name__}")
    if field.dim() < 2:
        raise ValueError(f"field must be shaped (..., H, W), got shape {tuple(field.shape)}")


def _checked_field(field: torch.Tensor) -> torch.Tensor:
    """`field` as a complex tensor (..., H, W) with finite values; complex128 stays complex128."""
    _check_shape(field)
    if not field.is_complex():
        field = field.to(torch.complex128 if field.dtype == torch.float64 else torch.complex64)
    # A sum is finite when every value is; only a non-finite sum (NaN/inf, or overflow) needs the full check.
    total = field.detach().sum()
    if not bool(torch.isfinite(total)) and not bool(torch.isfinite(torch.view_as_real(field.detach())).all()):
        raise ValueError("field contains NaN or inf; propagation needs finite values")
    return field


class Propagator:
    """Propagates fields of one shape over one distance at one wavelength; caches its transfer functions.

    Outside autograd it also keeps one zero-padded work buffer, reused from call to call: on a CPU a fresh
    zeroed buffer of the padded size costs about a third of an FFT. Not safe to call from two threads at once.
    """

    def __init__(
        self,
        shape: tuple[int, int],
        distance_m: float,
        wavelength_m: float,
        pitch_m: float | tuple[float, float],
        *,
        padding: Padding = "auto",
        band_limit: bool = True,
        aperture: float | None = None,
    ) -> None:
        self.plan = plan_propagation(shape, distance_m, wavelength_m, pitch_m,
                                     padding=padding, band_limit=band_limit, aperture=aperture)
        self._kernels: dict[tuple[torch.dtype, torch.device], torch.Tensor] = {}
        self._buffer: torch.Tensor | None = None

    def kernel(self, dtype: torch.dtype, device: torch.device | str) -> torch.Tensor:
        """The transfer function for this dtype and device, computed once and cached."""
        key = (dtype, torch.device(device))
        if key not in self._kernels:
            # A normal tensor even if first asked for under inference_mode, so later autograd can use it.
            with torch.inference_mode(False):
                self._kernels[key] = transfer_function(self.plan, dtype, device)
        return self._kernels[key]

    def _padded(self, field: torch.Tensor) -> torch.Tensor:
        """`field` followed by its guard band of zeros (the field sits in the top-left corner)."""
        (h, w), (ph, pw) = self.plan.shape, self.plan.padded_shape
        if (ph, pw) == (h, w):
            return field
        if torch.is_grad_enabled() and field.requires_grad:
            return torch.nn.functional.pad(field, (0, pw - w, 0, ph - h))
        shape = (*field.shape[:-2], ph, pw)
        buffer = self._buffer
        if buffer is None or buffer.shape != shape or buffer.dtype != field.dtype or buffer.device != field.device:
            with torch.inference_mode(False):
                buffer = self._buffer = field.new_zeros(shape)
        buffer[..., :h, :w] = field  # the guard band is never written, so it stays zero
        return buffer

    def __call__(self, field: torch.Tensor) -> torch.Tensor:
        """The field after propagation, same shape and complex dtype as `field`."""
        field = _checked_field(field)
        if tuple(field.shape[-2:]) != self.plan.shape:
            raise ValueError(f"field is {tuple(field.shape[-2:])}, this propagator is for {self.plan.shape}")
        if self.plan.distance_m == 0 and self.plan.aperture is None:
            return field.clone()
        spectrum = torch.fft.fft2(self._padded(field))
        # In place: the FFT's backward does not need its output, so autograd allows it.
        spectrum.mul_(self.kernel(spectrum.dtype, spectrum.device))
        h, w = self.plan.shape
        # A copy, not a view: a view would keep the whole padded grid alive as long as the result lives.
        return torch.fft.ifft2(spectrum)[..., :h, :w].contiguous()


_CACHE: OrderedDict[tuple, Propagator] = OrderedDict()
_CACHE_SIZE = 8  # each entry holds its kernels (and a work buffer): keep it small


def propagate(
    field: torch.Tensor,
    distance_m: float,
    wavelength_m: float,
    pitch_m: float | tuple[float, float],
    *,
    padding: Padding = "auto",
    band_limit: bool = True,
    aperture: float | None = None,
) -> torch.Tensor:
    """Propagate `field` (..., H, W) by `distance_m` (+z: SLM -> target) with a cached `Propagator`.

    `aperture`, if given, is a Fourier-plane iris (radius as a fraction of the grid's Nyquist frequency).
    """
    _check_shape(field)
    key = (tuple(field.shape[-2:]), float(distance_m), float(wavelength_m), _pair(pitch_m), padding, band_limit,
           aperture)
    prop = _CACHE.get(key)
    if prop is None:
        prop = Propagator(key[0], distance_m, wavelength_m, pitch_m, padding=padding, band_limit=band_limit,
                          aperture=aperture)
        _CACHE[key] = prop
        if len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    else:
        _CACHE.move_to_end(key)
    return prop(field)
