"""Propagation of one field to several planes: one forward FFT, then per plane one band-limited transfer function
and one inverse FFT, all planes in one batch.

Every plane is propagated as `Propagator` would propagate it alone (band-limited ASM, kernel phase in float64 with
the piston removed, evanescent components zeroed), on one padded grid shared by all planes: the one the padding
rule gives the farthest plane, which pads at least as much as every nearer plane needs. Each plane's band limit is
Matsushima's for its own distance on that grid. With a `window` (the ROI) only those outputs are computed, on the
smaller grid they need (`window_plan`), exactly as the whole field's propagation gives them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import torch

from benchctl.optics.plan import Padding, PropagationPlan, plan_propagation, window_plan
from benchctl.optics.propagation import GuardBand, _checked_field, transfer_function


def plane_plans(shape: tuple[int, int], distances_m: Sequence[float], wavelength_m: float,
                pitch_m: float | tuple[float, float], *, padding: Padding = "auto", band_limit: bool = True,
                aperture: float | None = None,
                window: tuple[int, int, int, int] | None = None) -> tuple[PropagationPlan, ...]:
    """One plan per distance, all on the padded grid of the plane that needs the most padding (per axis)."""
    if isinstance(distances_m, (str, bytes)) or not isinstance(distances_m, Sequence) or not distances_m:
        raise ValueError(f"distances_m must be a non-empty sequence of distances, got {distances_m!r}")
    plans = [plan_propagation(shape, float(d), wavelength_m, pitch_m, padding=padding, band_limit=band_limit,
                              aperture=aperture) for d in distances_m]
    rows, cols = max(p.padded_shape[0] for p in plans), max(p.padded_shape[1] for p in plans)
    (h, w) = plans[0].shape
    shared = [replace(p, padded_shape=(rows, cols), pad=(0, rows - h, 0, cols - w)) for p in plans]
    if window is not None:
        shared = [window_plan(p, window) for p in shared]
    return tuple(shared)


class MultiPlanePropagator:
    """Propagates fields of one shape to K planes at one wavelength: (..., H, W) -> (..., K, H, W) (the window's
    shape, if any). Caches its K transfer functions per dtype and device, and outside autograd keeps its work
    buffers (two padded grids); not safe to call from two threads at once.
    """

    def __init__(
        self,
        shape: tuple[int, int],
        distances_m: Sequence[float],
        wavelength_m: float,
        pitch_m: float | tuple[float, float],
        *,
        padding: Padding = "auto",
        band_limit: bool = True,
        aperture: float | None = None,
        window: tuple[int, int, int, int] | None = None,
    ) -> None:
        """`distances_m`: the planes (+z: SLM -> target), any order, repeats allowed; `window` = (row, rows, col,
        cols): compute only those outputs."""
        self.plans = plane_plans(shape, distances_m, wavelength_m, pitch_m, padding=padding, band_limit=band_limit,
                                 aperture=aperture, window=window)
        self.distances_m = tuple(p.distance_m for p in self.plans)
        self.plan = self.plans[0]  # grid, padding and window are the same for every plane
        self._kernels: dict[tuple[torch.dtype, torch.device], torch.Tensor] = {}
        self._padded = GuardBand(self.plan)
        self._buffer: torch.Tensor | None = None

    @property
    def output_shape(self) -> tuple[int, int]:
        """(rows, cols) of each plane's output: the window's, or the field's."""
        window = self.plan.window
        return (window[1], window[3]) if window is not None else self.plan.shape

    def kernels(self, dtype: torch.dtype, device: torch.device | str) -> torch.Tensor:
        """The K transfer functions (K, padded rows, padded cols) for this dtype and device, computed once."""
        key = (dtype, torch.device(device))
        if key not in self._kernels:
            with torch.inference_mode(False):  # filled plane by plane: a sweep's K kernels can be GiBs, held once
                kernels = torch.empty((len(self.plans), *self.plan.padded_shape), dtype=dtype, device=device)
                for k, plan in enumerate(self.plans):
                    kernels[k] = transfer_function(plan, dtype, device)
                self._kernels[key] = kernels
        return self._kernels[key]

    def __call__(self, field: torch.Tensor, pick: Sequence[int] | None = None) -> torch.Tensor:
        """The field at every plane, (..., K, rows, cols), same complex dtype as `field`; with `pick`, at those
        planes only (indices into `distances_m`, in that order)."""
        field = _checked_field(field)
        if tuple(field.shape[-2:]) != self.plan.shape:
            raise ValueError(f"field is {tuple(field.shape[-2:])}, this propagator is for {self.plan.shape}")
        kernels = self.kernels(field.dtype, field.device)
        if pick is not None:
            if not pick or any(not 0 <= k < len(kernels) for k in pick):
                raise ValueError(f"pick must name planes 0 .. {len(kernels) - 1}, got {list(pick)!r}")
            kernels = kernels[list(pick)]
        spectrum = torch.fft.fft2(self._padded(field))
        row, rows, col, cols = self.plan.window or (0, self.plan.shape[0], 0, self.plan.shape[1])
        if spectrum.requires_grad or spectrum.device.type != "cpu":  # one batch of K grids (cuFFT batches them)
            planes = torch.fft.ifft2(spectrum.unsqueeze(-3) * kernels)
            return planes[..., row:row + rows, col:col + cols].contiguous()
        # On a CPU outside autograd, one plane at a time: a working set of two padded grids, not K (K at once took 30 %
        # longer; an inverse FFT written into its input, 15 % longer than into a new grid: docs/depth.md).
        product = self._work_buffer(spectrum)
        out = spectrum.new_empty((*spectrum.shape[:-2], len(kernels), rows, cols))
        for k, kernel in enumerate(kernels):
            torch.mul(spectrum, kernel, out=product)
            out[..., k, :, :] = torch.fft.ifft2(product)[..., row:row + rows, col:col + cols]
        return out

    def _work_buffer(self, like: torch.Tensor) -> torch.Tensor:
        buffer = self._buffer
        if buffer is None or buffer.shape != like.shape or buffer.dtype != like.dtype or buffer.device != like.device:
            with torch.inference_mode(False):
                buffer = self._buffer = torch.empty_like(like)
        return buffer
