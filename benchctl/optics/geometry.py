"""The optical geometry of one colour channel, in SI units: what a hologram is computed for, and what a stored
calibration, a trained network and a cached hologram are valid for.

Torch-free: describing a profile and planning its propagations (`benchctl profile check`) load no torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any, Mapping

from benchctl.optics.plan import Padding, PropagationPlan, pitch_pair, plan_propagation

# Plausibility bounds: they catch values given in the wrong unit (520 for 520 nm, 3.74 for 3.74 um).
_WAVELENGTH_RANGE_M = (100e-9, 20e-6)
_PITCH_RANGE_M = (0.1e-6, 1e-3)


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
class Geometry:
    """One colour channel of the bench as numbers (SI units).

    `shape` is the SLM grid (H, W); `roi` is the (rows, cols) region of the target plane, centred on the grid,
    where the image must appear (the rest is "don't care"). `pitch_m` may be given as one number (square
    pixels); it is stored as (dy, dx). The target plane lies `distance_m` > 0 downstream of the SLM (+z).
    `aperture`: the Fourier-plane iris radius in units of the SLM's Nyquist frequency (None: no iris).
    """

    wavelength_m: float
    pitch_m: tuple[float, float]
    distance_m: float
    shape: tuple[int, int]
    roi: tuple[int, int]
    padding: Padding = "auto"
    aperture: float | None = None

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

    @property
    def geometry(self) -> Geometry:
        """The geometry alone (an `OpticalSetup` is a geometry with the measured bench and display added)."""
        return Geometry(self.wavelength_m, self.pitch_m, self.distance_m, self.shape, self.roi, self.padding,
                        self.aperture)

    def plan(self) -> PropagationPlan:
        """What the propagation SLM -> target plane computes at this geometry (padded grid, band limit)."""
        return plan_propagation(self.shape, self.distance_m, self.wavelength_m, self.pitch_m, padding=self.padding,
                                aperture=self.aperture)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, in SI units as held (exact through JSON): the fingerprint that calibrations, trained
        checkpoints and cached holograms record and are compared by."""
        return {"wavelength_m": self.wavelength_m, "pitch_m": list(self.pitch_m), "distance_m": self.distance_m,
                "shape": list(self.shape), "roi": list(self.roi), "padding": self.padding, "aperture": self.aperture}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Geometry:
        """The geometry `to_dict` recorded, or a record in the human units checkpoints used before (nm, um, mm)."""
        if "wavelength_nm" in data:
            data = {"wavelength_m": data["wavelength_nm"] * 1e-9, "pitch_m": [p * 1e-6 for p in data["pitch_um"]],
                    "distance_m": data["distance_mm"] * 1e-3, "shape": data["grid"], "roi": data["roi"],
                    "padding": data["padding"], "aperture": data["iris_fraction"]}
        aperture = data["aperture"]
        return cls(wavelength_m=data["wavelength_m"], pitch_m=pitch_pair(data["pitch_m"]),
                   distance_m=data["distance_m"], shape=_int_pair("shape", data["shape"]),
                   roi=_int_pair("roi", data["roi"]), padding=data["padding"],
                   aperture=None if aperture is None else _real("aperture", aperture))
