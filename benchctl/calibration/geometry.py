"""Profiles and their geometry: a profile on another SLM grid (training and benchmarks at a smaller scale),
geometries told apart in words (a checkpoint that does not fit names each difference), and the propagation each
channel of a profile will compute. Torch-free (`benchctl profile check` uses it).

The geometry itself is `optics.geometry.Geometry`, each channel's from `Profile.geometry`; `Geometry.to_dict`
is the one fingerprint that calibrations, checkpoints and cached holograms record.
"""

from __future__ import annotations

import math

import msgspec

from benchctl.optics.geometry import Geometry
from benchctl.profiles import Profile

_REL_TOL = 1e-6  # recorded values went through a unit conversion and a decimal text


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
    distance, depth_range = profile.optics.distance_mm, profile.optics.depth_range_mm
    if scale_distance:
        area = size[0] * size[1] / (h * w)
        # A depth offset d defocuses by d NA / pitch pixels: offsets scale with the grid's side, so that a scene's
        # blur keeps its size relative to the image, while the distance scales with the area (the near end kept
        # beyond half the distance where a small grid would bring it to the SLM).
        if depth_range is not None:
            near, far = (distance * area + (end - distance) * math.sqrt(area) for end in depth_range)
            depth_range = (max(near, 0.5 * distance * area), far)
        distance *= area
    return msgspec.structs.replace(
        profile,
        slm=msgspec.structs.replace(profile.slm, height=size[0], width=size[1]),
        optics=msgspec.structs.replace(profile.optics, roi=roi, distance_mm=distance, depth_range_mm=depth_range),
    )


def _num(value: float) -> str:
    return f"{value:.6g}"


def _pitch(value: tuple[float, float]) -> str:
    dy, dx = (p * 1e6 for p in value)
    return f"{_num(dy)} um" if math.isclose(dy, dx, rel_tol=_REL_TOL) else f"{_num(dy)} x {_num(dx)} um"


_FIELDS = (  # attribute, label, formatter (human units)
    ("wavelength_m", "wavelength", lambda v: f"{_num(v * 1e9)} nm"),
    ("pitch_m", "pitch", _pitch),
    ("distance_m", "distance", lambda v: f"{_num(v * 1e3)} mm"),
    ("shape", "grid", lambda v: f"{v[0]}x{v[1]}"),
    ("roi", "ROI", lambda v: f"{v[0]}x{v[1]}"),
    ("padding", "padding", repr),
    ("aperture", "iris", lambda v: "none" if v is None else f"{_num(v)} x Nyquist"),
)


def _same(a: object, b: object) -> bool:
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) and isinstance(b, float):
        return math.isclose(a, b, rel_tol=_REL_TOL)
    return a == b


def geometry_differences(recorded: Geometry, actual: Geometry, where: str) -> list[str]:
    """Each way `recorded` (a checkpoint's) and `actual` differ, as "pitch 3.74 um in the checkpoint, 8 um in
    <where>"; empty when they match."""
    return [f"{label} {fmt(getattr(recorded, name))} in the checkpoint, {fmt(getattr(actual, name))} in {where}"
            for name, label, fmt in _FIELDS if not _same(getattr(recorded, name), getattr(actual, name))]


def describe_plans(profile: Profile) -> str:
    """Per laser channel, what the propagation SLM -> target plane computes at the profile's geometry."""
    if profile.slm is None or profile.optics is None or not profile.channels:
        return "  Propagation SLM -> target: not described (needs [slm], [optics] and [laser])"
    lines = ["  Propagation SLM -> target (padding auto):"]
    lines += [f"    {channel.name}: {profile.geometry(channel.name).plan().describe()}" for channel in profile.channels]
    return "\n".join(lines)
