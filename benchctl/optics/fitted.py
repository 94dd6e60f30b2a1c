"""A propagation model fitted to captures: per colour, the wavefront error at the SLM (Zernike terms of
optics.aberration), the beam's amplitude (a Gaussian with waist and offset), the SLM's pixel crosstalk (a
Gaussian blur of the phase the panel drives) and its zero order (the fraction of the light it leaves unmodulated),
found by gradient descent through the differentiable propagation so that the model's target-plane intensity of
known phase patterns matches what the camera recorded of them (registered onto the target plane); or its intensity at
several planes, where the camera captured each pattern focused at each of them: defocus, spherical aberration and
the beam's curvature change the image with depth in ways one plane cannot tell apart.

`FittedOptics` is the result: an `OpticalSetup` carrying one (field_model) modulates the light by
(1 - f) e^(i C(phase)) + f and multiplies it by A e^(i W) before propagating, so SGD and every simulated score see
the bench as measured. Crosstalk acts where the driven phase jumps, i.e. where the gray levels wrap: it applies to
the phase the panel drives (`SLM.driven`), not to a hologram phase wrapped elsewhere.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from benchctl.optics.aberration import (
    ZERNIKE_TERMS,
    Pitch,
    crosstalk_blur,
    gaussian_beam_power,
    gaussian_blur,
    pupil_radius_m,
    zernike_basis,
)
from benchctl.optics.metrics import centred_slices
from benchctl.optics.multiplane import MultiPlanePropagator
from benchctl.optics.propagation import Propagator

# Below this blur (sigma, pixels) no spatial frequency of the driven phase changes by more than 0.05 %.
NEGLIGIBLE_CROSSTALK_PX = 0.01


@dataclass(frozen=True)
class FittedOptics:
    """One colour's fitted departure from the ideal model (hashable, so setups carrying it stay comparable)."""

    zernike_waves: tuple[tuple[str, float], ...] = ()  # (term, waves) pairs, ANSI/OSA RMS-normalised
    waist_m: float = 0.0  # Gaussian 1/e^2 radius of the beam; 0: uniform illumination
    offset_m: tuple[float, float] = (0.0, 0.0)  # (rows, cols) from the panel's centre to the beam's centre
    crosstalk_px: float = 0.0  # Gaussian blur (sigma, SLM pixels) of the driven phase: fringing fields
    zero_order: float = 0.0  # amplitude fraction the panel leaves unmodulated (pixel gaps)

    def slm_factor(self, shape: tuple[int, int], pitch_m: Pitch) -> torch.Tensor:
        """A e^(i W) on the SLM grid, complex64 (H, W): beam amplitude (mean power 1) and wavefront error."""
        amplitude = torch.ones(shape, dtype=torch.float64)
        if self.waist_m:
            power = gaussian_beam_power(shape, pitch_m, self.waist_m, self.offset_m)
            amplitude = (power / power.mean()).sqrt()
        names = [name for name, _ in self.zernike_waves]
        phase = torch.zeros(shape, dtype=torch.float64)
        if names:
            waves = torch.tensor([w for _, w in self.zernike_waves], dtype=torch.float64)
            phase = 2 * math.pi * torch.einsum("k,khw->hw", waves, zernike_basis(shape, pitch_m, names))
        return torch.polar(amplitude, phase).to(torch.complex64)

    @property
    def has_crosstalk(self) -> bool:
        """Whether the crosstalk matters: below NEGLIGIBLE_CROSSTALK_PX it is a fit's noise around none."""
        return self.crosstalk_px >= NEGLIGIBLE_CROSSTALK_PX

    def modulated(self, driven: torch.Tensor) -> torch.Tensor:
        """The panel's field under unit light for the phase it drives, (1 - f) e^(i C(driven)) + f: blurred by the
        crosstalk only when it matters (as optimisers then treat it: no FFTs on every reconstruction for nothing)."""
        phase = crosstalk_blur(driven, self.crosstalk_px) if self.has_crosstalk else driven
        field = torch.polar(torch.ones_like(phase), phase)
        return (1 - self.zero_order) * field + self.zero_order if self.zero_order else field

    def to_dict(self) -> dict[str, object]:
        """Profile units (waves, mm), as model calibration stores it."""
        return {"zernike_waves": dict(self.zernike_waves), "waist_mm": self.waist_m * 1e3,
                "offset_mm": [v * 1e3 for v in self.offset_m], "crosstalk_px": self.crosstalk_px,
                "zero_order": self.zero_order}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> FittedOptics:
        """The model of `to_dict`'s form: an entry of an optical-model.json, checked by the caller (the file's
        typed model is benchctl.calibration.files.FittedColour)."""
        waves = data.get("zernike_waves", {})
        offset = data.get("offset_mm", (0.0, 0.0))
        return cls(tuple((name, float(waves[name])) for name in ZERNIKE_TERMS if name in waves),
                   float(data.get("waist_mm", 0.0)) * 1e-3, (float(offset[0]) * 1e-3, float(offset[1]) * 1e-3),
                   float(data.get("crosstalk_px", 0.0)), float(data.get("zero_order", 0.0)))


class FitDiverged(ValueError):
    """The fit's loss or its model's field became non-finite (NaN or infinite): its learning rate is too large for these
    captures. Says at which step; `losses` holds the (finite) curve before it."""

    def __init__(self, step: int, total: int, losses: list[float], what: str) -> None:
        super().__init__(f"the fit diverged at step {step}/{total} ({what})")
        self.step, self.total, self.losses = step, total, losses


@dataclass
class FitResult:
    """A fit's outcome: the model, the relative RMS residual of the captures before and after, the loss curve, and
    the camera's blur (sigma, SLM pixels: part of the measurement, not of the bench that holograms see)."""

    model: FittedOptics
    residual: float
    initial_residual: float
    losses: list[float]
    camera_blur_px: float = 0.0


# The crosstalk parameter is its variance in units of CROSSTALK_UNIT_PX2, so that Adam's steps (of about the
# learning rate) move it by a fraction of a realistic value (sigma 0.05-0.3 px); a variance, so that its gradient
# does not vanish at 0 as sigma's does.
CROSSTALK_UNIT_PX2 = 0.1
ZERO_ORDER_UNIT = 0.1  # likewise for the zero order (realistic: 0.01-0.05 of the amplitude)
CAMERA_UNIT_PX2 = 1.0  # and the camera's blur (realistic: sigma 0.3-1 SLM pixel)


class _Model(torch.nn.Module):
    """The differentiable bench: zernike waves, log-waist and offset (both in units of the pupil radius), the
    crosstalk's variance and the zero order."""

    def __init__(self, shape: tuple[int, int], pitch_m: Pitch, terms: Sequence[str], beam: bool,
                 crosstalk: bool, zero_order: bool, camera_blur: bool) -> None:
        super().__init__()
        self.shape, self.pitch_m, self.terms, self.beam = shape, pitch_m, list(terms), beam
        self.crosstalk, self.unmodulated, self.camera_blur = crosstalk, zero_order, camera_blur
        self.radius = pupil_radius_m(shape, pitch_m)
        self.register_buffer("basis", zernike_basis(shape, pitch_m, self.terms))
        self.waves = torch.nn.Parameter(torch.zeros(len(self.terms), dtype=torch.float64))
        self.log_waist = torch.nn.Parameter(torch.tensor(math.log(4.0), dtype=torch.float64))  # nearly uniform
        self.offset = torch.nn.Parameter(torch.zeros(2, dtype=torch.float64))
        # The variance is |p| (a clamp at 0 could hold it there for good), started at 0.01: |p|'s gradient is 0 at 0.
        self.crosstalk_variance = torch.nn.Parameter(torch.tensor(0.01, dtype=torch.float64), requires_grad=crosstalk)
        self.zero_order = torch.nn.Parameter(torch.tensor(0.01, dtype=torch.float64), requires_grad=zero_order)
        self.camera_variance = torch.nn.Parameter(torch.tensor(0.01, dtype=torch.float64), requires_grad=camera_blur)

    def factor(self) -> torch.Tensor:
        phase = 2 * math.pi * torch.einsum("k,khw->hw", self.waves, self.basis)
        amplitude = torch.ones_like(phase)
        if self.beam:
            power = gaussian_beam_power(self.shape, self.pitch_m, self.log_waist.exp() * self.radius,
                                        self.offset * self.radius)
            amplitude = (power / power.mean()).sqrt()
        return torch.polar(amplitude, phase).to(torch.complex64)

    def fields(self, driven: torch.Tensor) -> torch.Tensor:
        """The SLM fields of the driven phases (N, H, W): blurred by the crosstalk, modulating all but the zero
        order, lit through `factor`."""
        if self.crosstalk:
            driven = gaussian_blur(driven.double(), self.crosstalk_variance.abs() * CROSSTALK_UNIT_PX2)
        field = torch.polar(torch.ones_like(driven, dtype=torch.float32), driven.float())
        if self.unmodulated:
            fraction = (self.zero_order.abs() * ZERO_ORDER_UNIT).float()
            field = (1 - fraction) * field + fraction
        return field * self.factor()

    def seen(self, intensity: torch.Tensor, smoothing_px2: float = 0.0) -> torch.Tensor:
        """The target-plane intensity as the registered capture shows it, blurred by the camera's optics, sampling
        and resampling (nuisance, not the bench's: holograms never see it); further smoothed by `smoothing_px2`."""
        variance = self.camera_variance.abs() * CAMERA_UNIT_PX2 if self.camera_blur else 0.0
        return gaussian_blur(intensity.double(), variance + smoothing_px2)

    def camera_blur_px(self) -> float:
        if not self.camera_blur:
            return 0.0
        return round(math.sqrt(abs(float(self.camera_variance.detach())) * CAMERA_UNIT_PX2), 5)

    def result(self) -> FittedOptics:
        waves = tuple((name, round(float(w), 5)) for name, w in zip(self.terms, self.waves.detach()))
        variance = abs(float(self.crosstalk_variance.detach())) * CROSSTALK_UNIT_PX2 if self.crosstalk else 0.0
        crosstalk = round(math.sqrt(variance), 5)
        zero_order = round(abs(float(self.zero_order.detach())) * ZERO_ORDER_UNIT, 5) if self.unmodulated else 0.0
        if not self.beam:
            return FittedOptics(waves, crosstalk_px=crosstalk, zero_order=zero_order)
        offset = self.offset.detach() * self.radius
        waist = float(self.log_waist.detach().exp()) * self.radius
        return FittedOptics(waves, waist, (float(offset[0]), float(offset[1])), crosstalk, zero_order)


def _residual(model_intensity: torch.Tensor, captured: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """Relative RMS misfit per image after the best gain and offset (exposure, stray light), or the best gain
    alone where `offset` (N,) is False: closed-form least squares of captured ~ g model (+ b), differentiable in the
    model. An image (N, ...) may be a stack of planes: one gain and offset for all of them (one pattern, one laser
    power and exposure, whatever the focus)."""
    m = model_intensity.flatten(1).double()
    c = captured.flatten(1).double()
    keep = offset.to(m.device).double()[:, None]
    m0, c0 = m - keep * m.mean(1, keepdim=True), c - keep * c.mean(1, keepdim=True)
    gain = (m0 * c0).sum(1, keepdim=True) / (m0.square().sum(1, keepdim=True) + 1e-30)
    misfit = (gain * m0 - c0).square().mean(1)
    return (misfit / c.square().mean(1)).sqrt()


def _checked(propagator: Propagator | MultiPlanePropagator, roi: tuple[int, int], phases: torch.Tensor,
             captured: torch.Tensor) -> tuple[slice, slice]:
    """The ROI's slices; ValueError where the captures do not match the patterns and the propagator's planes."""
    rows, cols = centred_slices(propagator.plan.shape, roi)
    planes = (len(propagator.plans),) if isinstance(propagator, MultiPlanePropagator) else ()
    wanted = (len(phases), *planes, *roi)
    if tuple(captured.shape) != wanted:
        raise ValueError(f"captures are {tuple(captured.shape)}, the patterns and planes need {wanted}")
    return rows, cols


def fit_optics(propagator: Propagator | MultiPlanePropagator, roi: tuple[int, int], phases: torch.Tensor,
               captured: torch.Tensor, *,
               terms: Sequence[str] = tuple(ZERNIKE_TERMS), beam: bool = True, crosstalk: bool = True,
               zero_order: bool = True, camera_blur: bool = True, dark_background: Sequence[bool] | None = None,
               iterations: int = 200, learning_rate: float = 0.02, smoothing_px: Sequence[float] = (2.0, 0.0),
               progress: Callable[[int, int], None] | None = None) -> FitResult:
    """Fit wavefront error, beam, crosstalk and zero order so that |P(A e^(iW) ((1 - f) e^(i blur(phase)) + f))|^2
    on the ROI matches `captured`.

    `phases` (N, H, W) are the driven phases of the displayed frames (`SLM.driven`: unwrapped where the gray levels
    do not wrap, so that the crosstalk blurs the jumps the panel has), `captured` (N, rows, cols) the registered
    captured intensity on the ROI (any scale, dark frame subtracted). With a `MultiPlanePropagator` to K planes,
    `captured` is (N, K, rows, cols): each pattern captured with the camera focused at each plane, one gain (and
    offset) per pattern for all its planes. Each image is compared after its best gain and
    offset, or gain alone where `dark_background` says so (a constant phase, whose light is the beam itself: a
    free offset would absorb the beam's curvature, which pins its waist). With `camera_blur` the model's intensity is
    blurred by a fitted Gaussian first, as the camera's optics, Bayer sampling and the registration's resampling
    blur the capture (left out, the crosstalk, which also softens the finest speckle, grows to imitate it). Adam on
    the mean relative residual; coarse to fine: the first stage compares the images blurred by `smoothing_px[0]`
    pixels (a smoother landscape for large aberrations), the last unblurred, its learning rate falling to zero
    (cosine). `progress(done, total)` is called after every step. A loss or a model field that becomes non-finite
    stops the fit (FitDiverged), which the propagation would otherwise meet as a NaN field.
    """
    offset = _offsets(dark_background, len(phases))
    shape = propagator.plan.shape
    rows, cols = _checked(propagator, roi, phases, captured)
    model = _Model(shape, propagator.plan.pitch_m, terms, beam, crosstalk, zero_order, camera_blur)
    optimiser = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=learning_rate)
    captured = captured.double()
    stages = [(sigma, iterations // len(smoothing_px)) for sigma in smoothing_px]
    total = sum(count for _, count in stages)
    losses: list[float] = []
    initial = None
    for stage, (sigma, steps) in enumerate(stages):
        target = gaussian_blur(captured, sigma**2)
        for step in range(steps):
            if stage == len(stages) - 1:  # the last stage settles: cosine to zero (constant Adam steps jitter)
                optimiser.param_groups[0]["lr"] = learning_rate * 0.5 * (1 + math.cos(math.pi * step / steps))
            optimiser.zero_grad()
            fields = model.fields(phases)
            if not bool(fields.isfinite().all()):
                raise FitDiverged(len(losses) + 1, total, losses, "its model's field became non-finite")
            intensity = propagator(fields).abs().square()[..., rows, cols]
            loss = _residual(model.seen(intensity, sigma**2), target, offset).mean()
            if initial is None:
                with torch.no_grad():
                    initial = float(_residual(intensity, captured, offset).mean())
            loss.backward()
            optimiser.step()
            losses.append(float(loss.detach()))
            if not math.isfinite(losses[-1]):
                raise FitDiverged(len(losses), total, losses[:-1], f"its loss became {losses[-1]}")
            if progress is not None:
                progress(len(losses), total)
    with torch.no_grad():
        intensity = propagator(model.fields(phases)).abs().square()[..., rows, cols]
        residual = float(_residual(model.seen(intensity), captured, offset).mean())
    return FitResult(model.result(), residual, initial if initial is not None else residual, losses,
                     model.camera_blur_px())


def model_residual(propagator: Propagator | MultiPlanePropagator, roi: tuple[int, int], phases: torch.Tensor,
                   captured: torch.Tensor, model: FittedOptics, *, camera_blur_px: float = 0.0,
                   dark_background: Sequence[bool] | None = None) -> float:
    """The relative RMS residual of `captured` under a given `model` (seen through the camera's blur), as
    `fit_optics` reports its own fit's: how well a stored model explains new captures, so that a new fit is
    compared with the model it would replace on the same images (at the planes `propagator` reaches)."""
    offset = _offsets(dark_background, len(phases))
    shape, pitch = propagator.plan.shape, propagator.plan.pitch_m
    rows, cols = _checked(propagator, roi, phases, captured)
    with torch.no_grad():
        intensity = propagator(model.modulated(phases) * model.slm_factor(shape, pitch)).abs().square()[..., rows, cols]
        seen = gaussian_blur(intensity.double(), camera_blur_px**2)
        return float(_residual(seen, captured.double(), offset).mean())


def _offsets(dark_background: Sequence[bool] | None, count: int) -> torch.Tensor:
    """Per pattern, whether its comparison takes a free offset (all but those marked dark_background)."""
    if dark_background is not None and len(dark_background) != count:
        raise ValueError(f"dark_background has {len(dark_background)} entries for {count} patterns")
    return torch.tensor([not dark for dark in dark_background] if dark_background is not None else [True] * count)


def calibration_patterns(propagator_to_slm: Propagator, roi: tuple[int, int], count: int, seed: int,
                         spacing_px: int = 6) -> torch.Tensor:
    """`count` phase patterns (N, H, W) for calibration: each focuses a random sparse set of points with random
    phases in the ROI (one point per spacing^2 pixels on average), so every capture shows the local point-spread
    function over the whole ROI plus the speckle between points, both sensitive to the wavefront and the beam."""
    shape = propagator_to_slm.plan.shape
    rows, cols = centred_slices(shape, roi)
    generator = torch.Generator().manual_seed(seed)
    fields = torch.zeros((count, *shape), dtype=torch.complex64)
    points = (torch.rand((count, *roi), generator=generator) < 1 / spacing_px**2).float()
    phase = 2 * math.pi * torch.rand((count, *roi), generator=generator)
    fields[:, rows, cols] = torch.polar(points, phase)
    return propagator_to_slm(fields).angle()
