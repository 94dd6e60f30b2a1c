"""What a propagation will compute, decided before anything big is computed: padded grid, guard bands, band
limit (the padding rule is explained in `benchctl.optics.propagation`). Plain numpy, no torch, so describing
a profile's propagation (`benchctl profile check`) stays light.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from numbers import Integral
from typing import Union

import numpy as np

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
    # Only the outputs in window = (row, rows, col, cols) are wanted (`window_plan`); the transfer function is
    # then that of the grid `kernel_shape`, folded onto the smaller `padded_shape`.
    window: tuple[int, int, int, int] | None = None
    kernel_shape: tuple[int, int] | None = None

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
            + (f", output window {self.window[1]}x{self.window[3]}" if self.window is not None else "")
        )


def pitch_pair(value: float | tuple[float, float] | list[float]) -> tuple[float, float]:
    """A pitch as (dy, dx): one number is square pixels."""
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
    dy, dx = pitch_pair(pitch_m)
    sy, sx = wavelength_m / (2.0 * dy), wavelength_m / (2.0 * dx)
    if distance_m == 0:
        return 0.0, 0.0
    cos_theta2 = 1.0 - sy * sy - sx * sx
    if cos_theta2 <= 0:
        return float("inf"), float("inf")
    scale = abs(distance_m) / math.sqrt(cos_theta2)
    return scale * sy / dy, scale * sx / dx


AUTO_TOLERANCE = 3.5e-3
"""Relative L2 error that "auto" allows the wrapped tails of a full-band field (both axes together, modelled):
chosen so that at the paper geometry the ROI error of "auto" stays within the 2x goal of that of "2x" while it
pads well under 2x's area (docs/propagation.md measures both)."""


def wrapped_tail_power(n: int, reach: float, guard: int) -> float:
    """Mean power per pixel that a guard band of `guard` zeros lets wrap around an axis of `n` pixels.

    The model: a full-band, unit-power, random-phase field (what a phase SLM shows). Its transfer function
    ends on a hard edge at +-Nyquist (or at the band limit, which moves the reach to half the padded extent),
    so beyond the reach K the impulse response is the two edges' diffraction tails,
    |1 / (d - K) - 1 / (d + K)| / (2 pi) at a distance d: slow (1 / (d - K)) just past K, 2 K / d^2 far out.
    Light from b pixels inside one edge lands a pixels inside the other after d = guard + 1 + a + b; the
    powers of all such pairs add (random phase), averaged over the axis and counted for both edges.
    """
    u = np.arange(2 * n - 1, dtype=np.float64)
    pairs = np.minimum(u + 1, 2 * n - 1 - u)  # how many (a, b) have a + b = u
    d = guard + 1 + u
    k = min(reach, (n + guard) / 2)
    tail = (1 / (d - k) - 1 / (d + k)) / (2 * math.pi)
    return float(2 * (pairs * tail**2).sum() / n)


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

    (Sizes with a single factor 2 are slower than their neighbours on a CPU: docs/propagation.md.)
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


def band_limit_frequency(m: int, pitch: float, distance_m: float, wavelength_m: float) -> float:
    """Matsushima's per-axis frequency limit for a padded extent of m samples (the transfer function's too)."""
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
    dy, dx = pitch_pair(pitch_m)
    if not (dy > 0 and dx > 0 and math.isfinite(dy) and math.isfinite(dx)):
        raise ValueError(f"pitch_m must be positive, got {pitch_m}")
    if aperture is not None and not (0 < aperture and math.isfinite(aperture)):
        raise ValueError(f"aperture must be a positive fraction of the Nyquist frequency, got {aperture}")
    ky, kx = reach_pixels(distance_m, wavelength_m, (dy, dx))
    gy, gx = _guard(padding, h, ky), _guard(padding, w, kx)
    ph, pw = h + gy, w + gx
    fractions = []
    for m, d in ((ph, dy), (pw, dx)):
        freqs = np.abs(np.fft.fftfreq(m, d=d))
        keep = freqs < 1.0 / wavelength_m
        if band_limit and distance_m != 0:
            keep &= freqs < band_limit_frequency(m, d, distance_m, wavelength_m)
        fractions.append(float(keep.mean()))
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


def window_plan(plan: PropagationPlan, window: tuple[int, int, int, int]) -> PropagationPlan:
    """The plan that computes only the outputs in `window` = (row, rows, col, cols), exactly as `plan` does
    (its transfer function, band limit and wrap-around), on the smallest grid that allows it.

    Outputs y of the window see inputs x through the offsets y - x, R + N - 1 of them per axis (R wanted, N
    input samples). On a grid of at least that many samples no two of those offsets wrap onto one another, so
    `plan`'s impulse response, kept at just those offsets and folded onto the smaller grid, gives the same
    outputs. Per axis the grid is the fast FFT size >= R + N - 1, or `plan`'s own where that is not smaller.
    """
    row, rows, col, cols = (int(v) for v in window)
    (h, w), (ph, pw) = plan.shape, plan.padded_shape
    if rows < 1 or cols < 1 or row < 0 or col < 0 or row + rows > h or col + cols > w:
        raise ValueError(f"window {window} (row, rows, col, cols) does not fit in the field {plan.shape}")
    shape = (min(ph, _fft_size(h + rows - 1)), min(pw, _fft_size(w + cols - 1)))
    return replace(plan, padded_shape=shape, window=(row, rows, col, cols), kernel_shape=plan.padded_shape)
