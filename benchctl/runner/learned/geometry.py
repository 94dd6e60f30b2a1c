"""The optical geometry a learned model is trained for: recorded in checkpoints, compared before every use.

A trained hologram network is only valid for the geometry it was trained at (wavelength, pitch, distance,
grid, ROI, padding, iris): it has learned one propagation. Checkpoints record that geometry per colour in
human units, and loading one for another geometry is refused with a message that names each difference
(a peer project silently ran models trained at the wrong pitch).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import msgspec

from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile

Geometry = dict[str, Any]
"""wavelength_nm, pitch_um (dy, dx), distance_mm, grid (H, W), roi (rows, cols), padding, iris_fraction."""

_REL_TOL = 1e-6


def grid_profile(profile: Profile, size: tuple[int, int], *, scale_distance: bool = False) -> Profile:
    """`profile` with its SLM grid changed to `size` (H, W) and its ROI scaled per axis with the grid.

    The pitch is kept. The distance is kept too (what the paper does when it trains at 1088p, 4K and 8K, all
    at 7 cm) unless `scale_distance`, which scales it by the grid's area ratio so that the Fresnel number
    (N pitch)^2 / (lambda z) stays that of the full bench (what the speed-vs-error benchmark wants).
    """
    profile.require("slm", "optics")
    assert profile.slm is not None and profile.optics is not None
    (h, w), (rh, rw) = profile.slm.shape, profile.optics.roi
    if tuple(size) == (h, w):
        return profile
    roi = (max(1, round(rh * size[0] / h)), max(1, round(rw * size[1] / w)))
    distance = profile.optics.distance_mm * (size[0] * size[1] / (h * w) if scale_distance else 1.0)
    return msgspec.structs.replace(
        profile,
        slm=msgspec.structs.replace(profile.slm, height=size[0], width=size[1]),
        optics=msgspec.structs.replace(profile.optics, roi=roi, distance_mm=distance),
    )


def geometry_of(setup: OpticalSetup) -> Geometry:
    """The geometry of one colour channel in human units (JSON-ready)."""
    return {
        "wavelength_nm": setup.wavelength_m * 1e9,
        "pitch_um": [p * 1e6 for p in setup.pitch_m],
        "distance_mm": setup.distance_m * 1e3,
        "grid": list(setup.shape),
        "roi": list(setup.roi),
        "padding": setup.padding,
        "iris_fraction": setup.aperture,
    }


def setup_from_geometry(geometry: Mapping[str, Any]) -> OpticalSetup:
    """The `OpticalSetup` a recorded geometry describes (the inverse of `geometry_of`)."""
    return OpticalSetup(
        wavelength_m=float(geometry["wavelength_nm"]) * 1e-9,
        pitch_m=tuple(float(p) * 1e-6 for p in geometry["pitch_um"]),  # type: ignore[arg-type]
        distance_m=float(geometry["distance_mm"]) * 1e-3,
        shape=tuple(int(v) for v in geometry["grid"]),  # type: ignore[arg-type]
        roi=tuple(int(v) for v in geometry["roi"]),  # type: ignore[arg-type]
        padding=geometry["padding"],
        aperture=None if geometry["iris_fraction"] is None else float(geometry["iris_fraction"]),
    )


def _num(value: float) -> str:
    return f"{value:.6g}"


def _pitch(value: list[float]) -> str:
    dy, dx = value
    return f"{_num(dy)} um" if math.isclose(dy, dx, rel_tol=_REL_TOL) else f"{_num(dy)} x {_num(dx)} um"


_FIELDS = (  # key, label, formatter
    ("wavelength_nm", "wavelength", lambda v: f"{_num(v)} nm"),
    ("pitch_um", "pitch", _pitch),
    ("distance_mm", "distance", lambda v: f"{_num(v)} mm"),
    ("grid", "grid", lambda v: f"{v[0]}x{v[1]}"),
    ("roi", "ROI", lambda v: f"{v[0]}x{v[1]}"),
    ("padding", "padding", lambda v: repr(v)),
    ("iris_fraction", "iris", lambda v: "none" if v is None else f"{_num(v)} x Nyquist"),
)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return math.isclose(float(a), float(b), rel_tol=_REL_TOL)
    return a == b


def geometry_differences(recorded: Mapping[str, Any], actual: Mapping[str, Any], where: str) -> list[str]:
    """Each field where `recorded` (the checkpoint's) and `actual` differ, as
    "pitch 3.74 um in the checkpoint, 8 um in <where>"; empty when they match."""
    return [f"{label} {fmt(recorded[key])} in the checkpoint, {fmt(actual[key])} in {where}"
            for key, label, fmt in _FIELDS if not _same(recorded.get(key), actual.get(key))]


def describe_geometry(geometry: Mapping[str, Any]) -> str:
    """One line: "680 nm, pitch 3.74 um, 70 mm, grid 1088x1920, ROI 880x1600, padding 'auto', iris 0.5 x Nyquist"."""
    parts = [fmt(geometry[key]) if key == "wavelength_nm" else f"{label} {fmt(geometry[key])}"
             for key, label, fmt in _FIELDS]
    return ", ".join(parts)
