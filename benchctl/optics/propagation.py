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

import functools
import math
from dataclasses import replace

import torch

from benchctl.optics.plan import (
    Padding,
    PropagationPlan,
    band_limit_frequency,
    pitch_pair,
    plan_propagation,
    window_plan,
)


def transfer_function(plan: PropagationPlan, dtype: torch.dtype = torch.complex64,
                      device: torch.device | str | None = None) -> torch.Tensor:
    """The band-limited ASM transfer function on the padded FFT grid (unshifted), as complex `dtype`.

    For a windowed plan (`window_plan`): the transfer function of `plan.kernel_shape`, whose impulse response
    (computed in float64) is folded onto the smaller padded grid at the offsets the window needs.
    """
    window, kernel_shape = plan.window, plan.kernel_shape
    if window is None or kernel_shape is None or kernel_shape == plan.padded_shape:
        return _transfer_function(plan, dtype, device)
    full = _transfer_function(replace(plan, padded_shape=kernel_shape), torch.complex128, device)
    response = torch.fft.ifft2(full)
    del full
    folded = response.new_zeros(plan.padded_shape)
    (row, rows, col, cols), (h, w) = window, plan.shape
    offset_y = torch.arange(row - h + 1, row + rows, device=response.device)
    offset_x = torch.arange(col - w + 1, col + cols, device=response.device)
    (m_y, m_x), (k_y, k_x) = plan.padded_shape, kernel_shape
    folded[(offset_y % m_y)[:, None], (offset_x % m_x)[None, :]] = \
        response[(offset_y % k_y)[:, None], (offset_x % k_x)[None, :]]
    return torch.fft.fft2(folded).to(dtype)


def _transfer_function(plan: PropagationPlan, dtype: torch.dtype, device: torch.device | str | None) -> torch.Tensor:
    """The band-limited ASM transfer function on `plan.padded_shape`.

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
        keep_y = fy.abs() < band_limit_frequency(m_y, dy, z, lam)
        keep_x = fx.abs() < band_limit_frequency(m_x, dx, z, lam)
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


class GuardBand:
    """Puts fields in the top-left corner of a plan's padded grid, followed by the guard band of zeros.

    Outside autograd it keeps one zero-padded work buffer, reused from call to call: on a CPU a fresh zeroed
    buffer of the padded size costs about a third of an FFT. Not safe to call from two threads at once.
    """

    def __init__(self, plan: PropagationPlan) -> None:
        self.shape, self.padded_shape = plan.shape, plan.padded_shape
        self._buffer: torch.Tensor | None = None

    def __call__(self, field: torch.Tensor) -> torch.Tensor:
        """`field` (..., H, W) followed by its guard band: (..., padded rows, padded cols)."""
        (h, w), (ph, pw) = self.shape, self.padded_shape
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


class Propagator:
    """Propagates fields of one shape over one distance at one wavelength; caches its transfer functions.

    Outside autograd it reuses one zero-padded work buffer (`GuardBand`). Not safe to call from two threads at
    once.
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
        window: tuple[int, int, int, int] | None = None,
    ) -> None:
        """`window` = (row, rows, col, cols): compute only those outputs, on the smaller grid they need
        (`window_plan`), exactly as the whole field's propagation would give them."""
        self.plan = plan_propagation(shape, distance_m, wavelength_m, pitch_m,
                                     padding=padding, band_limit=band_limit, aperture=aperture)
        if window is not None:
            self.plan = window_plan(self.plan, window)
        self._kernels: dict[tuple[torch.dtype, torch.device], torch.Tensor] = {}
        self._padded = GuardBand(self.plan)

    def kernel(self, dtype: torch.dtype, device: torch.device | str) -> torch.Tensor:
        """The transfer function for this dtype and device, computed once and cached."""
        key = (dtype, torch.device(device))
        if key not in self._kernels:
            # A normal tensor even if first asked for under inference_mode, so later autograd can use it.
            with torch.inference_mode(False):
                self._kernels[key] = transfer_function(self.plan, dtype, device)
        return self._kernels[key]

    def __call__(self, field: torch.Tensor) -> torch.Tensor:
        """The field after propagation, same shape and complex dtype as `field` (the window's shape, if any)."""
        field = _checked_field(field)
        if tuple(field.shape[-2:]) != self.plan.shape:
            raise ValueError(f"field is {tuple(field.shape[-2:])}, this propagator is for {self.plan.shape}")
        if self.plan.distance_m == 0 and self.plan.aperture is None:
            return field.clone()
        spectrum = torch.fft.fft2(self._padded(field))
        # In place: the FFT's backward does not need its output, so autograd allows it.
        spectrum.mul_(self.kernel(spectrum.dtype, spectrum.device))
        row, rows, col, cols = self.plan.window or (0, self.plan.shape[0], 0, self.plan.shape[1])
        # A copy, not a view: a view would keep the whole padded grid alive as long as the result lives.
        return torch.fft.ifft2(spectrum)[..., row:row + rows, col:col + cols].contiguous()


@functools.lru_cache(maxsize=8)  # each entry holds its kernels (and a work buffer): keep it small
def _cached_propagator(shape: tuple[int, int], distance_m: float, wavelength_m: float, pitch_m: tuple[float, float],
                       padding: Padding, band_limit: bool, aperture: float | None) -> Propagator:
    return Propagator(shape, distance_m, wavelength_m, pitch_m, padding=padding, band_limit=band_limit,
                      aperture=aperture)


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
    shape = (int(field.shape[-2]), int(field.shape[-1]))
    return _cached_propagator(shape, float(distance_m), float(wavelength_m), pitch_pair(pitch_m), padding, band_limit,
                              aperture)(field)


class PrunedPropagator:
    """A `Propagator` evaluated faster where most of its grid is known to be zero (the simulator's live view):
    `Propagator.__call__` with the same transfer function on the same
    padded grid, computed as one-dimensional FFTs that skip what is known to be zero: the guard band's rows on the
    way in, the spatial frequencies the transfer function zeroes (the Fourier iris, the band limit) both ways, and
    the rows and columns outside the output on the way out. The result is the propagator's to float32 rounding;
    with the iris at half the Nyquist frequency it takes about half the time. Keeps two work buffers: not safe to
    call from two threads at once."""

    def __init__(self, propagator: Propagator) -> None:
        plan = propagator.plan
        kernel = propagator.kernel(torch.complex64, "cpu")
        passed = kernel != 0
        # Per axis the frequencies that pass form one band around zero: indices [0, low) and [n - high, n).
        (self.low_y, self.high_y), (self.low_x, self.high_x) = (_band(passed.any(dim=1)), _band(passed.any(dim=0)))
        rows = torch.cat([kernel[:self.low_y], kernel[len(kernel) - self.high_y:]])
        self.kernel = torch.cat([rows[:, :self.low_x], rows[:, kernel.shape[1] - self.high_x:]], dim=1)
        self.shape, self.padded_shape = plan.shape, plan.padded_shape
        self.window = plan.window or (0, plan.shape[0], 0, plan.shape[1])
        (h, _), (ph, pw), cols = plan.shape, plan.padded_shape, self.low_x + self.high_x
        self._rows = torch.zeros((max(h, self.window[1]), pw), dtype=torch.complex64)  # input rows, then output rows
        self._cols = torch.zeros((ph, cols), dtype=torch.complex64)

    def __call__(self, field: torch.Tensor) -> torch.Tensor:
        (h, w), (ph, pw) = self.shape, self.padded_shape
        row, rows, col, cols = self.window
        low_y, high_y, low_x, high_x = self.low_y, self.high_y, self.low_x, self.high_x
        padded = self._rows[:h]
        padded[:, :w] = field
        padded[:, w:] = 0
        spectrum = torch.fft.fft(padded, dim=1)
        self._cols[:h, :low_x] = spectrum[:, :low_x]
        self._cols[:h, low_x:] = spectrum[:, pw - high_x:]
        self._cols[h:] = 0
        spectrum = torch.fft.fft(self._cols, dim=0)
        spectrum[:low_y] *= self.kernel[:low_y]
        spectrum[low_y:ph - high_y] = 0
        spectrum[ph - high_y:] *= self.kernel[low_y:]
        back = torch.fft.ifft(spectrum, dim=0)[row:row + rows]
        out = self._rows[:rows]
        out[:, :low_x] = back[:, :low_x]
        out[:, low_x:pw - high_x] = 0
        out[:, pw - high_x:] = back[:, low_x:]
        return torch.fft.ifft(out, dim=1)[:, col:col + cols].clone()


def _band(passed: torch.Tensor) -> tuple[int, int]:
    """(low, high) such that exactly the indices [0, low) and [n - high, n) of `passed` (in FFT order) are True; a
    set of any other shape is taken whole (nothing skipped, still exact)."""
    n = len(passed)
    low = int(torch.argmin(passed.int())) if not passed.all() else n
    high = int(torch.argmin(passed.flip(0).int())) if low < n else 0
    if low < n and bool(passed[low:n - high].any()):
        return n, 0
    return low, high
