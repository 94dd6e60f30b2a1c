"""Targets: bundled test charts, photographs and image files, prepared as amplitude on the SLM grid.

A target spec is `chart:<name>` (drawn at the requested size, deterministic, no files shipped),
`photo:<name>` (a photograph bundled inside scikit-image, the `photos` extra) or the path of an image file.
Targets are sRGB in [0, 1]; prepare_target turns them into what holograms aim for: linear intensity, resized to
the ROI in linear light, square-rooted to amplitude, zero-padded to the grid.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from benchctl.errors import BenchctlError, did_you_mean
from benchctl.images import read_image
from benchctl.optics.colour import srgb_to_linear
from benchctl.optics.metrics import centred_slices
from benchctl.profiles import LaserChannel

RGB_PLANES = ("red", "green", "blue")
CHART_PREFIX = "chart:"
PHOTO_PREFIX = "photo:"

BLACK_INTENSITY = float(srgb_to_linear(torch.tensor(0.5 / 255, dtype=torch.float64)))
"""Linear intensity of half an 8-bit sRGB step (about 1.5e-4): a channel whose brightest pixel is below it
would display as 0 on an 8-bit screen, so it counts as black and is neither computed nor exposed."""


def _centred_coords(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates relative to the image centre, as (H, 1) rows and (1, W) columns."""
    return np.arange(h)[:, None] - (h - 1) / 2, np.arange(w)[None, :] - (w - 1) / 2


def _smooth_stripes(wave: np.ndarray, pixels_per_radian: np.ndarray) -> np.ndarray:
    """Black/white stripes at the zero crossings of sin(wave), antialiased over about one pixel.

    sin(wave) times the local pixels-per-radian is the signed distance to the nearest edge in pixels; where
    stripes get finer than the pixels the amplitude drops and they fade to gray instead of aliasing.
    """
    return np.clip(0.5 + np.sin(wave) * pixels_per_radian, 0.0, 1.0)


def _siemens(h: int, w: int) -> np.ndarray:
    """Siemens star: 36 alternating sectors in a disc on black."""
    y, x = _centred_coords(h, w)
    r = np.hypot(y, x)
    cycles = 18
    radius = 0.45 * min(h, w)
    star = _smooth_stripes(cycles * np.arctan2(y, x), r / cycles)
    return star * np.clip(radius - r + 0.5, 0.0, 1.0)


def _wedge(h: int, w: int) -> np.ndarray:
    """Converging lines: a fan whose period shrinks linearly from h/8 px at the left edge to 1.5 px at the right."""
    y, x = _centred_coords(h, w)
    coarse, fine = max(h / 8, 4.0), 1.5
    focus = (w - 1) / 2 + (w - 1) * fine / (coarse - fine)  # x of the point the lines converge to
    spacing = coarse / (focus + (w - 1) / 2)  # angular period (one white + one black line), radians
    r = np.hypot(y, focus - x)
    return _smooth_stripes(2 * np.pi * np.arctan2(y, focus - x) / spacing, r * spacing / (2 * np.pi))


def _bars(h: int, w: int) -> np.ndarray:
    """Colour bars white, yellow, cyan, green, magenta, red, blue, black over a gray ramp (bottom quarter)."""
    colours = np.array(
        [[1, 1, 1], [1, 1, 0], [0, 1, 1], [0, 1, 0], [1, 0, 1], [1, 0, 0], [0, 0, 1], [0, 0, 0]], dtype=float
    )
    edges = np.linspace(0, w, len(colours) + 1).round().astype(int)
    image = np.empty((h, w, 3))
    image[:] = colours[np.searchsorted(edges, np.arange(w), side="right") - 1][None]
    ramp_top = h - h // 4
    image[ramp_top:] = np.linspace(0.0, 1.0, w)[None, :, None]
    return image


_TEXT_LINES = ("HOLOGRAM", "benchctl 0123456789", "The quick brown fox jumps over the lazy dog")


def _text(h: int, w: int) -> np.ndarray:
    """White text on black in three lines of decreasing size, each as wide as the others (90 % of W)."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    unit = [cv2.getTextSize(line, font, 1.0, 1) for line in _TEXT_LINES]
    # Line pitch 1.5 x text height; narrow the lines when their stack would not fit 90 % of H.
    height_per_width = sum(1.5 * (th + baseline) / tw for (tw, th), baseline in unit)
    width = min(0.9 * w, 0.9 * h / height_per_width)
    layout = []
    for line, ((tw, _), _) in zip(_TEXT_LINES, unit):
        thickness = max(1, round(width / tw))
        scale = width / tw
        scale *= width / cv2.getTextSize(line, font, scale, thickness)[0][0]  # strokes widen the text
        (tw, th), baseline = cv2.getTextSize(line, font, scale, thickness)
        layout.append((line, scale, thickness, tw, 1.5 * (th + baseline)))
    canvas = np.zeros((h, w), dtype=np.uint8)
    bottom = (h - sum(pitch for *_, pitch in layout)) / 2
    for line, scale, thickness, tw, pitch in layout:
        bottom += pitch
        origin = (round((w - tw) / 2), round(bottom - pitch / 4))
        cv2.putText(canvas, line, origin, font, scale, 255, thickness, cv2.LINE_AA)
    return canvas / 255.0


def _grid(h: int, w: int) -> np.ndarray:
    """Dot grid: white dots on black, centred, period min(H, W) / 12 (at least 8 px)."""
    y, x = _centred_coords(h, w)
    period = max(8.0, min(h, w) / 12)
    radius = max(1.5, period / 8)  # at least 1.5 px: a dot between pixel centres still reaches 1
    dy = (y + period / 2) % period - period / 2
    dx = (x + period / 2) % period - period / 2
    return np.clip(radius + 0.5 - np.hypot(dy, dx), 0.0, 1.0)


def _uniform(colour: tuple[float, float, float], h: int, w: int) -> np.ndarray:
    return np.broadcast_to(np.asarray(colour, dtype=float), (h, w, 3))


_CHARTS: dict[str, tuple[Callable[[int, int], np.ndarray], str]] = {
    "siemens": (_siemens, "Siemens star, 36 sectors (resolution in every direction)"),
    "wedge": (_wedge, "converging lines, period h/8 down to 1.5 px (resolution limit)"),
    "bars": (_bars, "colour bars incl. pure red/green/blue/white/black over a gray ramp"),
    "text": (_text, "white text in three sizes on black (OpenCV's font: differs between OpenCV 4 and 5)"),
    "grid": (_grid, "dot grid on black (sparse target, distortion)"),
    "white": (functools.partial(_uniform, (1.0, 1.0, 1.0)), "uniform white"),
    "red": (functools.partial(_uniform, (1.0, 0.0, 0.0)), "uniform pure red"),
    "green": (functools.partial(_uniform, (0.0, 1.0, 0.0)), "uniform pure green"),
    "blue": (functools.partial(_uniform, (0.0, 0.0, 1.0)), "uniform pure blue"),
}


@dataclass(frozen=True)
class Photo:
    """A photograph shipped inside the scikit-image wheel: its file there, its role here, and its licence."""

    file: str
    split: str  # "eval": held out, never trained on; "train": may be trained on
    description: str
    licence: str


_PHOTOS: dict[str, Photo] = {
    "astronaut": Photo("astronaut.png", "eval", "astronaut portrait, colour, 512x512", "NASA, public domain"),
    "coffee": Photo("coffee.png", "eval", "cup of coffee, colour, 400x600", "Rachel Michetti, CC0"),
    "chelsea": Photo("chelsea.png", "eval", "cat, colour, 300x451", "Stefan van der Walt, CC0"),
    "rocket": Photo("rocket.jpg", "eval", "rocket on the pad, colour, 427x640", "SpaceX, public domain"),
    "hubble": Photo("hubble_deep_field.jpg", "train", "Hubble deep field, colour, 872x1000", "NASA, public domain"),
    "retina": Photo("retina.jpg", "train", "retina fundus, colour, 1411x1411", "Häggström et al., CC0"),
    "ihc": Photo("ihc.png", "train", "immunohistochemistry stain, colour, 512x512",
                 "no known copyright restrictions (scikit-image)"),
    "camera": Photo("camera.png", "train", "cameraman, gray, 512x512", "Lav Varshney, CC0"),
    "brick": Photo("brick.png", "train", "brick wall texture, gray, 512x512", "CC0Textures, CC0"),
    "grass": Photo("grass.png", "train", "grass texture, gray, 512x512", "CC0Textures, CC0"),
    "gravel": Photo("gravel.png", "train", "gravel texture, gray, 512x512", "CC0Textures, CC0"),
    "clock": Photo("clock_motion.png", "train", "clock with motion blur, gray, 300x400",
                   "Stefan van der Walt, public domain"),
}


def photo_specs(split: str) -> list[str]:
    """`photo:<name>` specs of one split: "eval" (held out from training) or "train"."""
    if split not in ("eval", "train"):
        raise ValueError(f"photo split must be 'eval' or 'train', got {split!r}")
    return [f"{PHOTO_PREFIX}{name}" for name, photo in _PHOTOS.items() if photo.split == split]


def photo_path(spec: str) -> Path:
    """The file behind `photo:<name>` inside the installed scikit-image package (nothing is downloaded)."""
    name = spec[len(PHOTO_PREFIX):] if spec.startswith(PHOTO_PREFIX) else spec
    photo = _PHOTOS.get(name)
    if photo is None:
        known = [f"{PHOTO_PREFIX}{n}" for n in _PHOTOS]
        raise BenchctlError(f"unknown photo {spec!r}{did_you_mean(spec, known, _name)}; known photos: "
                            f"{', '.join(known)}")
    package = importlib.util.find_spec("skimage")
    if package is None or not package.submodule_search_locations:
        raise BenchctlError(f"{spec}: photographs come from scikit-image's bundled images; "
                            "install them with: pip install 'benchctl[photos]'")
    path = Path(next(iter(package.submodule_search_locations))) / "data" / photo.file
    if not path.is_file():
        raise BenchctlError(f"{spec}: {path} is missing from the installed scikit-image")
    return path


def _name(spec: str) -> str:
    """A target's name without its kind ("coffee" of "photo:coffee"), as misspellings are compared."""
    return spec.split(":", 1)[-1]


def list_targets() -> dict[str, str]:
    """Bundled chart and photo specs with a one-line description each, for help texts."""
    charts = {f"{CHART_PREFIX}{name}": doc for name, (_, doc) in _CHARTS.items()}
    photos = {f"{PHOTO_PREFIX}{name}": f"{p.description} ({'held out' if p.split == 'eval' else 'training'}"
              f" photo; {p.licence})" for name, p in _PHOTOS.items()}
    return charts | photos


def load_target(spec: str | Path, size: tuple[int, int]) -> np.ndarray:
    """A target as float32 (H, W, 3) sRGB in [0, 1], from `chart:<name>`, `photo:<name>` or an image file.

    Charts are drawn at size = (H, W). Photos and image files keep their own resolution: prepare_target resamples in
    linear light, and resampling here too would blur twice. 8/16-bit integer images are scaled by their
    maximum, float images clipped to [0, 1]; gray becomes three equal channels; alpha is dropped.
    """
    text = str(spec)
    if text.startswith(CHART_PREFIX):
        h, w = size
        if h <= 0 or w <= 0:
            raise ValueError(f"chart size must be positive, got {size!r}")
        entry = _CHARTS.get(text[len(CHART_PREFIX):])
        if entry is None:
            known = [CHART_PREFIX + name for name in _CHARTS]
            raise BenchctlError(f"unknown chart {text!r}{did_you_mean(text, known, _name)}; known charts: "
                                f"{', '.join(known)}")
        image = entry[0](h, w)
    else:
        hint = "" if text.startswith(PHOTO_PREFIX) or Path(text).exists() else did_you_mean(text, list_targets(), _name)
        if hint:  # "coffee" for photo:coffee
            raise BenchctlError(f"{text}: no such file or target{hint}")
        image = read_image(photo_path(text) if text.startswith(PHOTO_PREFIX) else text)
        if np.issubdtype(image.dtype, np.floating) and not np.isfinite(image).all():
            bad = int((~np.isfinite(image)).sum())
            raise BenchctlError(f"{text}: {bad} NaN or infinite value(s); a target image must be finite")
        if np.issubdtype(image.dtype, np.integer):
            image = image / np.iinfo(image.dtype).max
        image = np.clip(image, 0.0, 1.0)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    return np.ascontiguousarray(image[:, :, :3], dtype=np.float32)


def prepare_target(srgb: np.ndarray, grid_shape: tuple[int, int], roi: tuple[int, int]) -> torch.Tensor:
    """Target amplitude float32 (3, H, W) on the grid: sRGB -> linear -> resized to the ROI -> sqrt -> padded.

    The image is stretched to the ROI (aspect ratio not kept), with area averaging when shrinking, and
    centred in a zero field of grid_shape, as the paper prepares its targets.
    """
    if srgb.ndim != 3 or srgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) sRGB image, got shape {srgb.shape}")
    rows, cols = centred_slices(grid_shape, roi)
    # A copy: a flip leaves negative strides, which a 1-pixel-high array keeps even through np.ascontiguousarray.
    linear = srgb_to_linear(torch.tensor(srgb.copy(), dtype=torch.float32)).numpy()
    if linear.shape[:2] != tuple(roi):
        shrinking = roi[0] < linear.shape[0] or roi[1] < linear.shape[1]
        interpolation = cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
        linear = cv2.resize(linear, (roi[1], roi[0]), interpolation=interpolation)
    amplitude = torch.zeros((3, *grid_shape), dtype=torch.float32)
    amplitude[:, rows, cols] = torch.from_numpy(linear).permute(2, 0, 1).clamp(min=0.0).sqrt()
    return amplitude


def active_channels(amplitude: torch.Tensor, threshold: float = BLACK_INTENSITY) -> list[bool]:
    """For each colour channel of (C, H, W) amplitude: True unless its peak intensity (amplitude^2) < threshold."""
    peak = amplitude.detach().flatten(1).abs().amax(dim=1)
    return [bool(p * p >= threshold) for p in peak]


def target_plane(channel: LaserChannel) -> int:
    """Which plane of an RGB target laser channel `channel` displays: by name, else by wavelength band."""
    if channel.name in RGB_PLANES:
        return RGB_PLANES.index(channel.name)
    if channel.wavelength_nm >= 590:
        return 0
    return 1 if channel.wavelength_nm >= 490 else 2
