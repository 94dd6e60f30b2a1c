"""Only the planes a scene needs: the bench's axial resolution, and the planes that resolve a scene's depth content.

A scene whose depth is continuous (a tilted plane, a photograph's depth map) has no depth at which a few fixed planes
show it: a pixel between two planes is judged at the nearer one, out of its own focus. So `choose_planes` also says,
per plane, the depths of its cluster an optimiser moves it through, one step per iteration (`DepthSweep`): over the
iterations every depth of the scene is scored near itself, at the cost of the same number of planes per iteration.

The axial resolution (docs/depth.md derives it): light converging to an image point at distance z arrives within
a cone of numerical aperture NA = min(a lambda / (2 pitch), N pitch / (2 z)) per axis (a: the iris radius in
Nyquist units, 1 without an iris; N pitch: the SLM's extent), whose depth of focus is lambda / NA^2 (using the
larger of the two axes' NA: the finer resolution). Points closer than that in depth are seen in focus at one plane.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from benchctl.optics.geometry import Geometry

MAX_PLANES = 16
"""The most planes `choose_planes` gives a scene; deeper content is spread evenly over that many."""
SWEEP_STEP = 0.25
"""A sweep's depths lie this many axial resolutions apart, and a plane scores the pixels within this many of it
(docs/depth.md measures the choice)."""
MAX_SWEEP_DEPTHS = 96
"""The most depths a sweep holds: each keeps a transfer function (54 MiB at full size), so a deep scene's sweep takes
wider steps instead of more memory (docs/depth.md measures what wider steps cost in focus)."""
MIN_LIGHT_SHARE = 0.01
"""A depth cluster holding less of the scene's light than this gets no plane of its own (its pixels go to the
nearest plane): a few stray pixels, such as the resampled edge of a layer, do not cost a propagation per frame."""


def numerical_aperture(geometry: Geometry) -> tuple[float, float]:
    """(rows, cols) NA of the light reaching the target plane: the grating's (or the iris's) largest angle, or the
    SLM's extent seen from the plane, whichever is smaller."""
    iris = 1.0 if geometry.aperture is None else min(1.0, geometry.aperture)
    return tuple(min(iris * geometry.wavelength_m / (2 * pitch), n * pitch / (2 * geometry.distance_m))
                 for n, pitch in zip(geometry.shape, geometry.pitch_m))  # type: ignore[return-value]


def axial_resolution_m(geometry: Geometry) -> float:
    """The depth of focus lambda / NA^2 at this geometry, NA the larger of the two axes' (`numerical_aperture`)."""
    return geometry.wavelength_m / max(numerical_aperture(geometry)) ** 2


@dataclass(frozen=True)
class DepthSweep:
    """Where an optimiser moves a scene's planes, from one iteration to the next: per plane the depths (metres,
    ascending) it steps through, and how far from a plane a pixel's depth may lie for it to be scored there."""

    depths_m: tuple[tuple[float, ...], ...]
    reach_m: float

    @property
    def all_m(self) -> tuple[float, ...]:
        """Every depth of the sweep, plane by plane (the order `at`'s indices count in)."""
        return tuple(z for depths in self.depths_m for z in depths)

    def at(self, iteration: int) -> tuple[list[int], tuple[float, ...]]:
        """Where the planes stand at `iteration` (their indices into `all_m`, and the depths): each steps through
        its depths in turn, cyclically, half a cycle out of step with the plane before it (so that the gap between
        neighbours changes from one iteration to the next)."""
        picks, start = [], 0
        for k, depths in enumerate(self.depths_m):
            picks.append(start + (iteration + k * (len(depths) // 2)) % len(depths))
            start += len(depths)
        every = self.all_m
        return picks, tuple(every[i] for i in picks)


@dataclass(frozen=True)
class PlaneChoice:
    """The planes (metres from the SLM, ascending) a scene is shown at, one line saying why, and (a scene with
    continuous depth) the sweep an optimiser moves them through."""

    planes_m: tuple[float, ...]
    reason: str
    sweep: DepthSweep | None = None

    @property
    def depths_m(self) -> tuple[float, ...]:
        """Every depth an optimiser propagates to: the sweep's, else the planes."""
        return self.planes_m if self.sweep is None else self.sweep.all_m


def _sweep(spans: Sequence[tuple[float, float]], resolution_m: float) -> DepthSweep | None:
    """Per span (nearest, farthest depth of a plane's pixels), depths SWEEP_STEP resolutions apart from end to end,
    or wider apart where that would make more than MAX_SWEEP_DEPTHS (each span's rounding up adds one depth at most,
    its end another); None where every span is one depth (layers: their planes need no sweep)."""
    spare = MAX_SWEEP_DEPTHS - 2 * len(spans)
    step = max(SWEEP_STEP * resolution_m, sum(high - low for low, high in spans) / max(spare, 1))
    depths = tuple(tuple(low + (high - low) * k / n for k in range(n + 1)) if n else (low,)
                   for low, high in spans for n in [math.ceil((high - low) / step - 1e-9)])
    return DepthSweep(depths, step) if any(len(d) > 1 for d in depths) else None


def _steps(sweep: DepthSweep | None, resolution_m: float) -> str:
    """How many depths a sweep holds and how far apart, and whether MAX_SWEEP_DEPTHS widened its steps."""
    if sweep is None:
        return ""
    widened = f", wider than {SWEEP_STEP:g} resolution to keep {MAX_SWEEP_DEPTHS} depths at most" \
        if sweep.reach_m > SWEEP_STEP * resolution_m * (1 + 1e-9) else ""
    return f" ({len(sweep.all_m)} depths, at most {sweep.reach_m * 1e3:.3g} mm apart{widened})"


def _lit(depth_m: torch.Tensor, light: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Depths and light of the pixels that carry light, sorted by depth (all pixels, equally, where none does)."""
    depth, weight = depth_m.detach().double().flatten(), light.detach().double().flatten()
    if not bool((weight > 0).any()):
        weight = torch.ones_like(weight)
    keep = weight > 0
    depth, weight = depth[keep], weight[keep]
    order = torch.argsort(depth)
    return depth[order], weight[order]


def even_planes(depth_m: torch.Tensor, light: torch.Tensor, count: int) -> PlaneChoice:
    """`count` planes evenly from the nearest to the farthest lit depth (one: halfway)."""
    if count < 1:
        raise ValueError(f"a scene needs at least one plane, got {count}")
    depth, _ = _lit(depth_m, light)
    near, far = float(depth[0]), float(depth[-1])
    planes: tuple[float, ...]
    if count == 1 or far == near:
        planes = (0.5 * (near + far),)
    else:
        planes = tuple(near + (far - near) * k / (count - 1) for k in range(count))
    return PlaneChoice(planes, f"{len(planes)} plane(s) evenly over the scene's depth {near * 1e3:.2f} .. "
                               f"{far * 1e3:.2f} mm, as asked")


def choose_planes(depth_m: torch.Tensor, light: torch.Tensor, resolution_m: float, *,
                  max_planes: int = MAX_PLANES) -> PlaneChoice:
    """The fewest planes that put every lit pixel within half the axial resolution of one of them.

    `light` (same shape as the depth) weighs each pixel (its intensity: dark pixels have no focus to show). From
    the nearest lit depth, each plane takes the pixels up to one resolution deeper and sits halfway between the
    nearest and farthest of them (a flat scene: exactly at its depth); a cluster with less than MIN_LIGHT_SHARE of
    the light is left to its neighbours. More than `max_planes` clusters: `max_planes` planes evenly over the lit
    depth. Where a plane's pixels span more than one depth, the choice holds the sweep over them (`DepthSweep`).
    """
    if not resolution_m > 0:
        raise ValueError(f"the axial resolution must be > 0, got {resolution_m!r}")
    lit = light > 0 if bool((light > 0).any()) else torch.ones_like(light, dtype=torch.bool)
    near, far = float(depth_m[lit].min()), float(depth_m[lit].max())
    why = (f"lit depth {near * 1e3:.2f} .. {far * 1e3:.2f} mm, axial resolution {resolution_m * 1e3:.3g} mm "
           f"(lambda / NA^2)")
    if far - near <= resolution_m:  # a flat scene: no sorting
        return PlaneChoice((0.5 * (near + far),), f"{why}: 1 plane at {0.5e3 * (near + far):.2f} mm")
    depth, weight = _lit(depth_m, light)
    total = float(weight.sum())
    clusters: list[tuple[float, float, float]] = []  # (nearest, farthest, light share)
    start = 0
    while start < len(depth):
        stop = int(torch.searchsorted(depth, depth[start] + resolution_m, right=True))
        clusters.append((float(depth[start]), float(depth[stop - 1]), float(weight[start:stop].sum()) / total))
        start = stop
    kept = [c for c in clusters if c[2] >= MIN_LIGHT_SHARE] or [max(clusters, key=lambda c: c[2])]
    if len(kept) > max_planes:
        planes = even_planes(depth_m, light, max_planes).planes_m
        edges = [near, *(0.5 * (a + b) for a, b in zip(planes, planes[1:])), far]
        sweep = _sweep(list(zip(edges, edges[1:])), resolution_m)
        return PlaneChoice(planes, f"{why}: {len(kept)} depth clusters, more than {max_planes}: {max_planes} planes "
                                   f"evenly, each swept over its share of the depth{_steps(sweep, resolution_m)}",
                           sweep)
    planes = tuple(0.5 * (low + high) for low, high, _ in kept)
    sweep = _sweep([(low, high) for low, high, _ in kept], resolution_m)
    dropped = len(clusters) - len(kept)
    note = f" ({dropped} cluster(s) under {MIN_LIGHT_SHARE:.0%} of the light left to their neighbours)" if dropped \
        else ""
    listed = ", ".join(f"{z * 1e3:.2f}" for z in planes)
    swept = f", each swept over its cluster{_steps(sweep, resolution_m)}" if sweep else ""
    return PlaneChoice(planes, f"{why}: {len(planes)} plane(s) at {listed} mm{swept}{note}", sweep)


def finest_resolution_m(geometries: Sequence[Geometry]) -> float:
    """The smallest axial resolution over the colours: planes shared by all colours must resolve the finest."""
    return min(axial_resolution_m(g) for g in geometries)

