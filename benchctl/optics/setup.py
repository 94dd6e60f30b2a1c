"""The optical geometry a hologram is computed for: wavelength, SLM grid and pitch, distance, region of interest."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from numbers import Integral, Real
from typing import TYPE_CHECKING, Union

import torch

from benchctl.optics.fitted import FittedOptics
from benchctl.optics.metrics import centred_slices
from benchctl.optics.propagation import Propagator

if TYPE_CHECKING:  # optics imports nothing else from benchctl at run time; a profile is only read here
    from benchctl.profiles import Profile

Padding = Union[str, int]

# Plausibility bounds: they catch values given in the wrong unit (520 for 520 nm, 3.74 for 3.74 um).
_WAVELENGTH_RANGE_M = (100e-9, 20e-6)
_PITCH_RANGE_M = (0.1e-6, 1e-3)

REACH_TOLERANCE_RAD = 0.05
"""A phase the SLM shows further than this from the one asked for lies in a gap of its table: no gray level comes
near it (a panel whose stroke falls short of 2 pi at this wavelength). Rounding to the nearest level of an 8-bit
table moves a phase by at most 0.02 rad (0.04 where a table's levels are three times sparser than the mean)."""


def _real(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, Real):
        raise ValueError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    return value


def _in_range(name: str, value: float, bounds: tuple[float, float], unit_hint: str) -> float:
    low, high = bounds
    if not low <= value <= high:
        raise ValueError(f"{name}={value:g} is outside {low:g}..{high:g} m; {unit_hint}")
    return value


def _int_pair(name: str, value: object) -> tuple[int, int]:
    if not isinstance(value, (tuple, list)) or len(value) != 2:
        raise ValueError(f"{name} must be a pair (rows, cols), got {value!r}")
    if any(isinstance(v, bool) or not isinstance(v, Integral) or v < 1 for v in value):
        raise ValueError(f"{name} must be two positive integers, got {value!r}")
    return int(value[0]), int(value[1])


@dataclass(frozen=True)
class OpticalSetup:
    """One colour channel of the bench as the hologram algorithms see it (SI units).

    `shape` is the SLM grid (H, W); `roi` is the (rows, cols) region of the target plane, centred on the grid,
    where the image must appear (the rest is "don't care"). `pitch_m` may be given as one number (square
    pixels); it is stored as (dy, dx). The target plane lies `distance_m` > 0 downstream of the SLM (+z).
    """

    wavelength_m: float
    pitch_m: tuple[float, float]
    distance_m: float
    shape: tuple[int, int]
    roi: tuple[int, int]
    padding: Padding = "auto"
    aperture: float | None = None  # Fourier-plane iris radius in units of the SLM's Nyquist frequency
    # The bench as measured (model calibration): beam amplitude and wavefront error applied to every SLM field.
    field_model: FittedOptics | None = None
    # What the SLM shows of a hologram phase (its lookup table's quantisation), when optimisers should see it.
    display: Callable[[torch.Tensor], torch.Tensor] | None = None
    _to_target: Propagator = field(init=False, repr=False, compare=False)
    _to_slm: Propagator = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        wavelength = _in_range("wavelength_m", _real("wavelength_m", self.wavelength_m), _WAVELENGTH_RANGE_M,
                               "give the wavelength in metres (520 nm = 520e-9)")
        raw_pitch = self.pitch_m if isinstance(self.pitch_m, (tuple, list)) else (self.pitch_m, self.pitch_m)
        if len(raw_pitch) != 2:
            raise ValueError(f"pitch_m must be a number or a pair (dy, dx), got {self.pitch_m!r}")
        pitch = tuple(_in_range("pitch_m", _real("pitch_m", p), _PITCH_RANGE_M,
                                "give the pixel pitch in metres (3.74 um = 3.74e-6)") for p in raw_pitch)
        distance = _real("distance_m", self.distance_m)
        if distance <= 0:
            raise ValueError(f"distance_m must be > 0 (the target plane lies downstream of the SLM), got {distance}")
        shape = _int_pair("shape", self.shape)
        roi = _int_pair("roi", self.roi)
        if roi[0] > shape[0] or roi[1] > shape[1]:
            raise ValueError(f"roi {roi} does not fit in the SLM grid {shape}")
        for name, value in (("wavelength_m", wavelength), ("pitch_m", pitch), ("distance_m", distance),
                            ("shape", shape), ("roi", roi)):
            object.__setattr__(self, name, value)
        # Built now so that a bad `padding` fails here; transfer functions are computed on first use and cached.
        object.__setattr__(self, "_to_target", self._propagator(distance))
        object.__setattr__(self, "_to_slm", self._propagator(-distance))

    @classmethod
    def from_profile(cls, profile: Profile, channel: str, padding: Padding = "auto") -> "OpticalSetup":
        """The setup of one laser channel of a hardware profile (profile units converted to SI), with the channel's
        fitted optical model if the profile names one (`optics.model`, set from calibration/<profile>/; the profile
        reads and checks the file)."""
        laser = profile.channel(channel)
        entry = profile.fitted_model(laser.name)
        model = FittedOptics.from_dict(entry) if entry is not None else None
        return cls(wavelength_m=laser.wavelength_m, pitch_m=profile.slm.pitch_m, distance_m=profile.optics.distance_m,
                   shape=profile.slm.shape, roi=profile.optics.roi, padding=padding,
                   aperture=profile.optics.iris_fraction, field_model=model)

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
        propagator = self.__dict__.get("_to_roi")
        if propagator is None:
            rows, cols = self.roi_slices
            propagator = Propagator(self.shape, self.distance_m, self.wavelength_m, self.pitch_m,
                                    padding=self.padding, aperture=self.aperture,
                                    window=(rows.start, self.roi[0], cols.start, self.roi[1]))
            object.__setattr__(self, "_to_roi", propagator)
        return propagator

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
        the loss is computed elsewhere. Red SGD, 70 steps at 1088 x 1920 on a panel reaching 0.88 x 2 pi at
        680 nm: 29.15 dB without this, 34.60 dB with it (docs/model_calibration.md)."""
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
        factor = self.__dict__.get("_slm_factor")
        if factor is None:
            factor = (self.field_model.slm_factor(self.shape, self.pitch_m) if self.field_model is not None
                      else torch.ones(self.shape, dtype=torch.complex64))
            object.__setattr__(self, "_slm_factor", factor)
        return factor
