"""Scenes with depth (RGB-D targets): an image and a depth map, bundled or the user's own, put on the bench.

A scene spec is `rgbd:<name>` for a bundled scene (drawn at the requested size, deterministic, no files shipped;
`photo` needs the `photos` extra) or `rgbd:<file>.toml` for a user's scene file:

    image = "street.png"        # any image a 2D target may be, relative to this file
    depth = "street-depth.png"  # 16-bit gray PNG: 0 = near_mm, 65535 = far_mm; or .npy: millimetres (float)
    near_mm = 66.0              # needed by a PNG; a .npy's values must lie within them if given
    far_mm = 74.0

Depth is the distance from the SLM along the optical axis. The bench shows depths inside its profile's
`optics.depth_range_mm`: bundled scenes are drawn in fractions of that range (0 = its near end), a user's scene in
millimetres must lie inside it, or is mapped linearly onto it when asked (`fit_depth`); `Scene.note` says so in
one line.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import cv2
import msgspec
import numpy as np
import torch

from benchctl.errors import BenchctlError, did_you_mean
from benchctl.images import read_image
from benchctl.optics.metrics import centred_slices
from benchctl.schema import Model, decode
from benchctl.targets import load_target, prepare_target

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

RGBD_PREFIX = "rgbd:"


@dataclass(frozen=True)
class Scene:
    """An RGB-D scene: sRGB (H, W, 3) float32 in [0, 1], depth (H, W) float64 in metres from the SLM, and a line
    saying what was done to its depth to put it on the bench (None: nothing)."""

    spec: str
    srgb: np.ndarray
    depth_m: np.ndarray
    note: str | None = None

    @property
    def depth_span_m(self) -> tuple[float, float]:
        """The nearest and farthest depth in the scene."""
        return float(self.depth_m.min()), float(self.depth_m.max())


def _chart(name: str, h: int, w: int) -> np.ndarray:
    return load_target(f"chart:{name}", (h, w))


def _side_by_side(h: int, w: int, charts: tuple[str, ...], depths: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Charts in vertical bands of equal width, each band at its own relative depth."""
    edges = np.linspace(0, w, len(charts) + 1).round().astype(int)
    image, depth = np.zeros((h, w, 3), np.float32), np.zeros((h, w))
    for (left, right), chart, z in zip(zip(edges[:-1], edges[1:]), charts, depths):
        image[:, left:right] = _chart(chart, h, right - left)
        depth[:, left:right] = z
    return image, depth


def _flat(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    return _chart("siemens", h, w), np.full((h, w), 0.5)


def _two_planes(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    return _side_by_side(h, w, ("siemens", "text"), (0.1, 0.9))


def _three_planes(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    return _side_by_side(h, w, ("siemens", "bars", "grid"), (0.0, 0.5, 1.0))


def _tilted(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """A checkerboard (squares of h / 12 px, antialiased) on a plane whose depth runs from 0 at the left edge to 1
    at the right."""
    y, x = np.mgrid[0:h, 0:w] + 0.5
    period = max(4.0, h / 6)
    wave = np.sin(2 * np.pi * y / period) * np.sin(2 * np.pi * x / period)
    board = np.clip(0.5 + wave * period / (2 * np.pi), 0.0, 1.0)
    return np.repeat(board[:, :, None], 3, axis=2).astype(np.float32), np.repeat(np.linspace(0, 1, w)[None], h, 0)


def _occlusion(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Text on a far layer (depth 0.2) partly hidden behind a disc holding a Siemens star on a near one (0.8):
    nearer the camera, which looks from beyond the planes towards the SLM."""
    image, depth = _chart("text", h, w).copy(), np.full((h, w), 0.2)
    y, x = np.mgrid[0:h, 0:w] - np.array([(h - 1) / 2, (w - 1) / 2])[:, None, None]
    disc = np.hypot(y, x) < 0.3 * min(h, w)
    star = _chart("siemens", h, w)
    image[disc] = 0.25 + 0.75 * star[disc]  # the disc is lit where the star is dark: the layer hides what is behind
    depth[disc] = 0.8
    return image, depth


def _photo(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """photo:coffee with a ground-plane depth: its top row at 0, its bottom row at 1."""
    image = load_target("photo:coffee", (h, w))
    rows = image.shape[0]
    return image, np.repeat(np.linspace(0, 1, rows)[:, None], image.shape[1], 1)


_SCENES: dict[str, tuple[Callable[[int, int], tuple[np.ndarray, np.ndarray]], str]] = {
    "flat": (_flat, "Siemens star on one plane in the middle of the depth range"),
    "two-planes": (_two_planes, "Siemens star (left) and text (right) at 10 % and 90 % of the depth range"),
    "three-planes": (_three_planes, "Siemens star, colour bars and dot grid at 0, 50 and 100 % of the depth range"),
    "tilted": (_tilted, "checkerboard on a plane tilted across the whole depth range, left to right"),
    "occlusion": (_occlusion, "text at 20 % of the depth range, partly hidden behind a disc with a star at 80 %"),
    "photo": (_photo, "photo:coffee with a ground-plane depth, top at the near end, bottom at the far end "
                      "(the photos extra)"),
}


def list_scenes() -> dict[str, str]:
    """Bundled scene specs with a one-line description each, for help texts."""
    return {f"{RGBD_PREFIX}{name}": doc for name, (_, doc) in _SCENES.items()}


def is_scene(spec: str | Path) -> bool:
    """Whether a target spec names a scene with depth."""
    return str(spec).startswith(RGBD_PREFIX)


DepthMm = Annotated[float, msgspec.Meta(gt=0)]


class SceneFile(Model, kw_only=True):
    """A user's RGB-D scene file (TOML): the image, the depth map and the depths its ends stand for."""

    image: Path
    depth: Path
    near_mm: DepthMm | None = None
    far_mm: DepthMm | None = None


def load_scene(spec: str, size: tuple[int, int], depth_range_m: tuple[float, float] | None, *,
               fit_depth: bool = False) -> Scene:
    """The scene `spec` names (`rgbd:<name>` or `rgbd:<file>.toml`), its depth on the bench.

    Bundled scenes are drawn at `size` (H, W) in fractions of `depth_range_m` (near, far); a user's scene keeps its
    resolution and its millimetres, and must lie within `depth_range_m` unless `fit_depth` maps its near .. far
    onto it. No depth range (None): the bench shows one plane, and every scene with depth is refused.
    """
    if not is_scene(spec):
        raise BenchctlError(f"{spec}: a scene with depth is named rgbd:<name> or rgbd:<scene file>.toml")
    if depth_range_m is None:
        raise BenchctlError(f"{spec}: this bench shows one plane only: set optics.depth_range_mm = [near, far] in its "
                            "profile to show scenes with depth")
    near, far = depth_range_m
    name = spec[len(RGBD_PREFIX):]
    if name in _SCENES:
        h, w = size
        srgb, relative = _SCENES[name][0](h, w)
        note = f"{spec}: drawn across the bench's depth range {near * 1e3:g} .. {far * 1e3:g} mm"
        return Scene(spec, np.ascontiguousarray(srgb, np.float32), near + (far - near) * relative, note)
    path = Path(name)
    if path.suffix.lower() != ".toml" or not path.is_file():
        hint = did_you_mean(spec, list_scenes(), lambda text: text[len(RGBD_PREFIX):])
        raise BenchctlError(f"{spec}: no bundled scene or scene file of that name{hint}; bundled scenes: "
                            f"{', '.join(list_scenes())}; or rgbd:<file>.toml (image, depth, near_mm, far_mm)")
    return _user_scene(spec, path, depth_range_m, fit_depth)


def _user_scene(spec: str, path: Path, depth_range_m: tuple[float, float], fit_depth: bool) -> Scene:
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as error:
        raise BenchctlError(f"{path}: not a readable TOML scene file: {error}") from None
    scene = decode(raw, SceneFile, path)
    if scene.near_mm is not None and scene.far_mm is not None and not scene.near_mm < scene.far_mm:
        raise BenchctlError(f"{path}: near_mm {scene.near_mm:g} must be less than far_mm {scene.far_mm:g}")
    srgb = load_target(scene.image, (1, 1))
    depth_mm = _depth_mm(scene)
    if depth_mm.shape != srgb.shape[:2]:
        raise BenchctlError(f"{scene.depth}: depth map is {depth_mm.shape[0]}x{depth_mm.shape[1]}, the image "
                            f"{scene.image} is {srgb.shape[0]}x{srgb.shape[1]}: they must be the same size")
    near, far = depth_range_m
    low, high = float(depth_mm.min()), float(depth_mm.max())
    bench = f"the bench's depth range {near * 1e3:g} .. {far * 1e3:g} mm (optics.depth_range_mm)"
    if near * 1e3 <= low and high <= far * 1e3:
        return Scene(spec, srgb, depth_mm * 1e-3)
    if not fit_depth:
        raise BenchctlError(f"{path}: its depth {low:g} .. {high:g} mm lies outside {bench}; map it onto the range "
                            "with --fit-depth")
    start = scene.near_mm if scene.near_mm is not None else low
    stop = scene.far_mm if scene.far_mm is not None else high
    relative = (depth_mm - start) / (stop - start) if stop > start else np.full_like(depth_mm, 0.5)
    note = f"{spec}: depth {start:g} .. {stop:g} mm mapped onto {bench}"
    return Scene(spec, srgb, near + (far - near) * relative, note)


def _depth_mm(scene: SceneFile) -> np.ndarray:
    """The depth map of a scene file in millimetres (float64), checked."""
    path = scene.depth
    if path.suffix.lower() == ".npy":
        try:
            values = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as error:
            raise BenchctlError(f"{path}: not a readable .npy depth map: {error}") from None
        if values.ndim != 2 or values.dtype.kind not in "fiu":
            raise BenchctlError(f"{path}: a depth map must be 2-D numbers (H, W), got {values.dtype} {values.shape}")
        depth = values.astype(np.float64)
        bad = ~np.isfinite(depth)
        if bad.any():
            row, col = np.argwhere(bad)[0]
            raise BenchctlError(f"{path}: {int(bad.sum())} depth value(s) are NaN or infinite (first at row {row}, "
                                f"column {col}: {depth[row, col]})")
        low_ok = scene.near_mm if scene.near_mm is not None else 0.0
        high_ok = scene.far_mm if scene.far_mm is not None else np.inf
        outside = (depth <= 0) | (depth < low_ok) | (depth > high_ok)
        if outside.any():
            row, col = np.argwhere(outside)[0]
            allowed = f"{low_ok:g} .. {high_ok:g} mm" if scene.near_mm is not None or scene.far_mm is not None \
                else "> 0 mm"
            raise BenchctlError(f"{path}: depth {depth[row, col]:g} mm at row {row}, column {col} is outside "
                                f"{allowed} ({int(outside.sum())} value(s) are)")
        return depth
    gray = read_image(path)
    if gray.ndim != 2:
        raise BenchctlError(f"{path}: a depth map must be one gray channel, got {gray.shape[2]} channels")
    if gray.dtype != np.uint16:
        raise BenchctlError(f"{path}: a depth PNG must be 16-bit (0 = near_mm, 65535 = far_mm), got {gray.dtype}")
    if scene.near_mm is None or scene.far_mm is None:
        raise BenchctlError(f"{path}: a 16-bit depth map needs near_mm and far_mm in the scene file (what 0 and 65535 "
                            "stand for)")
    return scene.near_mm + (scene.far_mm - scene.near_mm) * gray.astype(np.float64) / 65535.0


def prepare_scene(scene: Scene, grid_shape: tuple[int, int], roi: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Target amplitude float32 (3, H, W) on the grid as `prepare_target` makes it, and the depth (H, W) float64 in
    metres: resized to the ROI by nearest neighbour (no depth between two layers is invented at an edge) and
    continued outside it by its edge values."""
    amplitude = prepare_target(scene.srgb, grid_shape, roi)
    depth = scene.depth_m
    if depth.shape != tuple(roi):
        depth = cv2.resize(depth, (roi[1], roi[0]), interpolation=cv2.INTER_NEAREST)
    rows, cols = centred_slices(grid_shape, roi)
    padded = np.pad(depth, ((rows.start, grid_shape[0] - rows.stop), (cols.start, grid_shape[1] - cols.stop)),
                    mode="edge")
    return amplitude, torch.from_numpy(np.ascontiguousarray(padded, dtype=np.float64))
