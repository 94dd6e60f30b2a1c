"""Propagation of one field to several planes: one forward FFT, then per plane one band-limited transfer function
and one inverse FFT; on a GPU all planes in one batch, on a CPU one plane at a time (under autograd too, through the
adjoint written out: a working set of a few padded grids instead of K).

Every plane is propagated as `Propagator` would propagate it alone (band-limited ASM, kernel phase in float64 with
the piston removed, evanescent components zeroed), on one padded grid shared by all planes: the one the padding
rule gives the farthest plane, which pads at least as much as every nearer plane needs. Each plane's band limit is
Matsushima's for its own distance on that grid. With a `window` (the ROI) only those outputs are computed, on the
smaller grid they need (`window_plan`), exactly as the whole field's propagation gives them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

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
        every = self.kernels(field.dtype, field.device)
        if pick is not None and (not pick or any(not 0 <= k < len(every) for k in pick)):
            raise ValueError(f"pick must name planes 0 .. {len(every) - 1}, got {list(pick)!r}")
        kernels = [every[k] for k in (range(len(every)) if pick is None else pick)]  # views: a sweep's are GiBs
        if field.device.type != "cpu":  # one batch of K grids (cuFFT batches them)
            planes = torch.fft.ifft2(torch.fft.fft2(self._padded(field)).unsqueeze(-3) * torch.stack(kernels))
            return planes[..., self._rows, self._cols].contiguous()
        if torch.is_grad_enabled() and field.requires_grad:
            return _PlanesOneByOne.apply(field, self, kernels)
        return self._one_by_one(field, kernels)

    @property
    def _rows(self) -> slice:
        row, rows = self.plan.window[:2] if self.plan.window else (0, self.plan.shape[0])
        return slice(row, row + rows)

    @property
    def _cols(self) -> slice:
        col, cols = self.plan.window[2:] if self.plan.window else (0, self.plan.shape[1])
        return slice(col, col + cols)

    def _one_by_one(self, field: torch.Tensor, kernels: Sequence[torch.Tensor]) -> torch.Tensor:
        """The planes one at a time, building no graph: a working set of two padded grids, not K (K at once took 30 %
        longer; an inverse FFT written into its input, 15 % longer than into a new grid: docs/depth.md)."""
        spectrum = torch.fft.fft2(self._padded(field))
        product = self._work_buffer(spectrum)
        out = spectrum.new_empty((*spectrum.shape[:-2], len(kernels), *self.output_shape))
        for k, kernel in enumerate(kernels):
            torch.mul(spectrum, kernel, out=product)
            out[..., k, :, :] = torch.fft.ifft2(product)[..., self._rows, self._cols]
        return out

    def _adjoint(self, grad: torch.Tensor, kernels: Sequence[torch.Tensor]) -> torch.Tensor:
        """The gradient with respect to the field of the planes' gradient `grad` (..., K, rows, cols): the adjoint
        crop -> FFT -> conjugate kernel, summed over the planes, then one inverse FFT and the field's corner (the
        transforms' 1/N factors cancel), one plane at a time."""
        placed = grad.new_zeros((*grad.shape[:-3], *self.plan.padded_shape))
        total = torch.zeros_like(placed)
        for k, kernel in enumerate(kernels):
            placed[..., self._rows, self._cols] = grad[..., k, :, :]
            total.addcmul_(torch.fft.fft2(placed), kernel.conj())
        h, w = self.plan.shape
        return torch.fft.ifft2(total)[..., :h, :w]

    def _work_buffer(self, like: torch.Tensor) -> torch.Tensor:
        buffer = self._buffer
        if buffer is None or buffer.shape != like.shape or buffer.dtype != like.dtype or buffer.device != like.device:
            with torch.inference_mode(False):
                buffer = self._buffer = torch.empty_like(like)
        return buffer


class _PlanesOneByOne(torch.autograd.Function):
    """`MultiPlanePropagator` on a CPU under autograd, one plane at a time both ways: autograd's batch kept K padded
    products and K inverse transforms for the backward pass; this keeps the kernels it already caches."""

    @staticmethod
    def forward(ctx: Any, field: torch.Tensor, propagator: MultiPlanePropagator,
                kernels: Sequence[torch.Tensor]) -> torch.Tensor:
        ctx.propagator, ctx.kernels = propagator, kernels
        return propagator._one_by_one(field, kernels)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        return ctx.propagator._adjoint(grad, ctx.kernels), None, None
