"""An optical setup: one colour channel's geometry with the bench as measured (a fitted optical model) and what
the SLM shows of a phase; its propagators, and the one simulation of a hologram everyone uses."""

from __future__ import annotations

import copy
import dataclasses
import functools
import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

from benchctl.optics.fitted import FittedOptics
from benchctl.optics.geometry import Geometry
from benchctl.optics.metrics import centred_slices
from benchctl.optics.multiplane import MultiPlanePropagator
from benchctl.optics.propagation import Propagator

REACH_TOLERANCE_RAD = 0.05
"""A phase the SLM shows further than this from the one asked for lies in a gap of its table: no gray level comes
near it (a panel whose stroke falls short of 2 pi at this wavelength). Larger than the rounding to the nearest
level of an 8-bit table, even where its levels are three times sparser than the mean."""

_PLANE_CACHE_SIZE = 4  # multi-plane propagators kept per setup: each holds K transfer functions


@dataclass(frozen=True)
class OpticalSetup(Geometry):
    """One colour channel of the bench as the hologram algorithms see it: its `Geometry` (SI units), the bench as
    measured (`field_model`) and what the SLM shows of a phase (`display`)."""

    # The bench as measured (model calibration): beam amplitude and wavefront error applied to every SLM field.
    field_model: FittedOptics | None = None
    # What the SLM shows of a hologram phase (its lookup table's quantisation), when optimisers should see it.
    display: Callable[[torch.Tensor], torch.Tensor] | None = None
    _to_target: Propagator = field(init=False, repr=False, compare=False)
    _to_slm: Propagator = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        # Built now so that a bad `padding` fails here; transfer functions are computed on first use and cached.
        object.__setattr__(self, "_to_target", self._propagator(self.distance_m))
        object.__setattr__(self, "_to_slm", self._propagator(-self.distance_m))

    @classmethod
    def of(cls, geometry: Geometry, field_model: FittedOptics | None = None) -> OpticalSetup:
        """The setup of `geometry`, lit through `field_model` (None: the ideal bench)."""
        values = {item.name: getattr(geometry, item.name) for item in dataclasses.fields(Geometry)}
        return cls(**values, field_model=field_model)

    def with_display(self, display: Callable[[torch.Tensor], torch.Tensor] | None) -> "OpticalSetup":
        """This setup with `display` (the SLM's `display_model`), sharing its propagators, their cached transfer
        functions and the SLM factor (built here first, so that a setup reused across frames keeps them)."""
        if display is None:
            return self
        self.roi_propagator()
        self.slm_factor()
        twin = copy.copy(self)
        object.__setattr__(twin, "display", display)
        return twin

    def _propagator(self, distance_m: float) -> Propagator:
        return Propagator(self.shape, distance_m, self.wavelength_m, self.pitch_m, padding=self.padding,
                          aperture=self.aperture)

    def target_propagator(self) -> Propagator:
        """The cached propagator SLM -> target plane (+z)."""
        return self._to_target

    def roi_propagator(self) -> Propagator:
        """The propagator SLM -> target plane (+z) that computes only the ROI, built on first use and cached."""
        return self._to_roi

    @functools.cached_property
    def _to_roi(self) -> Propagator:
        rows, cols = self.roi_slices
        return Propagator(self.shape, self.distance_m, self.wavelength_m, self.pitch_m, padding=self.padding,
                          aperture=self.aperture, window=(rows.start, self.roi[0], cols.start, self.roi[1]))

    def planes_propagator(self, distances_m: Sequence[float], *, roi: bool = False) -> MultiPlanePropagator:
        """The propagator SLM -> the planes at `distances_m` (+z), of the whole grid or (`roi`) of the ROI only,
        built on first use and cached (the last few plane sets)."""
        key = (tuple(float(d) for d in distances_m), roi)
        cache: OrderedDict[tuple[tuple[float, ...], bool], MultiPlanePropagator] = \
            self.__dict__.setdefault("_planes", OrderedDict())
        propagator = cache.get(key)
        if propagator is None:
            rows, cols = self.roi_slices
            window = (rows.start, self.roi[0], cols.start, self.roi[1]) if roi else None
            propagator = MultiPlanePropagator(self.shape, key[0], self.wavelength_m, self.pitch_m,
                                              padding=self.padding, aperture=self.aperture, window=window)
            cache[key] = propagator
            if len(cache) > _PLANE_CACHE_SIZE:
                cache.popitem(last=False)
        else:
            cache.move_to_end(key)
        return propagator

    def release_planes(self) -> None:
        """Drops this setup's cached multi-plane propagators (and so those of any display twin made after they were
        cached, which shares them): a deep scene's sweep holds GiBs of transfer functions, which the next colour must
        not find still held."""
        self.__dict__.get("_planes", {}).clear()

    def at_distance(self, distance_m: float) -> OpticalSetup:
        """This setup (fitted model and display included) with its target plane at `distance_m`: itself where that
        is its own distance; built once per distance and cached."""
        if float(distance_m) == self.distance_m:
            return self
        # Keyed by the display too: `with_display` twins share this cache (and the propagators in it).
        twins: dict[tuple[float, object], OpticalSetup] = self.__dict__.setdefault("_at_distance", {})
        key = (float(distance_m), self.display)
        if key not in twins:
            twins[key] = dataclasses.replace(self, distance_m=float(distance_m))
        return twins[key]

    def slm_propagator(self) -> Propagator:
        """The cached propagator target plane -> SLM (-z)."""
        return self._to_slm

    @property
    def roi_slices(self) -> tuple[slice, slice]:
        """Row and column slices of the centred ROI: `x[..., rows, cols]` crops a (..., H, W) tensor to it."""
        return centred_slices(self.shape, self.roi)

    def reconstruct(self, phase: torch.Tensor) -> torch.Tensor:
        """Amplitude at the target plane of a phase-only hologram lit by a unit plane wave: |P_{+z}(exp(i phase))|;
        with a fitted model, lit by its beam through its wavefront error, the phase blurred by its crosstalk C and
        a fraction f of the light unmodulated: |P_{+z}(A e^(i W) ((1 - f) exp(i C(phase)) + f))|, where `phase`
        should be what the panel drives (`SLM.driven`).

        The one simulation of a hologram everyone uses; differentiable, and its gradient stays finite where the
        amplitude is exactly zero (complex abs, not a square root of the intensity).
        """
        return self.target_propagator()(self.slm_field(phase)).abs()

    def reconstruct_roi(self, phase: torch.Tensor) -> torch.Tensor:
        """`reconstruct(phase)` on the ROI only, computed on the smaller grid that the ROI needs (`window_plan`):
        what every loss and score that looks only at the ROI uses."""
        return self.roi_propagator()(self.slm_field(phase)).abs()

    def reconstruct_planes(self, phase: torch.Tensor, distances_m: Sequence[float]) -> torch.Tensor:
        """The focal stack of a phase: `reconstruct(phase)` at each of the planes `distances_m` (+z from the SLM),
        shaped (..., K, H, W), from one SLM field through one forward FFT (`MultiPlanePropagator`)."""
        return self.planes_propagator(distances_m)(self.slm_field(phase)).abs()

    def reconstruct_planes_roi(self, phase: torch.Tensor, distances_m: Sequence[float],
                               pick: Sequence[int] | None = None) -> torch.Tensor:
        """`reconstruct_planes` on the ROI only, (..., K, rows, cols), on the smaller grid the ROI needs; `pick`: at
        those of the planes only (indices into `distances_m`; the propagator, its transfer functions cached, is the
        one for all of them)."""
        return self.planes_propagator(distances_m, roi=True)(self.slm_field(phase), pick).abs()

    def displayed(self, phase: torch.Tensor) -> torch.Tensor:
        """`phase` as the SLM shows it (`display`), its gradient passed straight through the quantisation, so an
        optimiser moves the phase it asked for while scoring the one shown; `phase` itself without `display`."""
        if self.display is None:
            return phase
        return phase + (self.display(phase.detach()) - phase).detach()

    def within_reach(self, phase: torch.Tensor) -> torch.Tensor:
        """`phase` with every value the SLM cannot show (more than REACH_TOLERANCE_RAD from what it shows) replaced
        by the phase it shows there, the rest unchanged (an optimiser's steps below one gray level survive).

        Optimisers apply it after each step. The straight-through gradient of `displayed` cannot see a table's
        gap: a phase inside it is shown at the gap's edge whatever small step it takes, so it stays there while
        the loss is computed elsewhere (docs/model_calibration.md measures what this gains)."""
        if self.display is None:
            return phase
        step = torch.remainder(self.display(phase.detach()) - phase + math.pi, 2 * math.pi) - math.pi
        return torch.where(step.abs() > REACH_TOLERANCE_RAD, phase + step, phase)

    def slm_field(self, phase: torch.Tensor) -> torch.Tensor:
        """The complex field leaving the SLM that shows `phase`: exp(i phase), or with a fitted model
        A e^(i W) ((1 - f) exp(i C(phase)) + f)."""
        if self.field_model is None:
            return torch.polar(torch.ones_like(phase), phase)
        return self.field_model.modulated(phase) * self.slm_factor().to(phase.device)

    def without_wavefront(self, phase: torch.Tensor) -> torch.Tensor:
        """`phase` minus the fitted model's wavefront error W (unchanged without a model): what to display so that
        the measured bench lights the SLM as an ideal one would, up to its beam's amplitude. Learned networks,
        trained as translation-invariant maps, cannot learn a position-dependent W; it is taken out here."""
        if self.field_model is None:
            return phase
        return phase - self.slm_factor().angle().to(phase.device)

    def slm_factor(self) -> torch.Tensor:
        """The fitted model's A e^(i W) on the SLM grid (complex64), computed once; ones without a model."""
        return self._slm_factor

    @functools.cached_property
    def _slm_factor(self) -> torch.Tensor:
        return (self.field_model.slm_factor(self.shape, self.pitch_m) if self.field_model is not None
                else torch.ones(self.shape, dtype=torch.complex64))
