"""Training images for the learned methods: a folder of image files, or procedural images anyone may redistribute.

`--data DIR` takes every image file in DIR (not its subfolders), sorted by name; point it at DIV2K (the
paper's training set at 1080p) or your own pictures. `--data procedural:N` draws N images instead:
"dead leaves" pictures (occluding discs, ellipses and polygons of random colour and size, with sizes drawn
from a power law, so edges appear at every scale as in natural images) over a smooth colour gradient or a
black background, some shapes striped, some lines of text. They are drawn deterministically from the image
index alone, at whatever size is asked, so `procedural:N` means the same N pictures everywhere and needs no
files; `python -m benchctl.training.data OUTDIR --count N` writes them as PNGs to look at or to reuse.
`--data photos:train` takes the 8 training photographs bundled in scikit-image (`benchctl.targets.photo_specs`;
`photos:eval` names the 4 held-out ones, meant for evaluation only). Specs join with "+", e.g.
`procedural:64+photos:train`.

Scenes with depth, for the networks that read one (`benchctl.cgh.learned.depth`): `--data procedural-rgbd:N` draws
N random RGB-D scenes (`procedural_scene`), again from the index alone: procedural pictures as textures on a
background plane (fronto-parallel, tilted or a ground plane) and on 1-4 occluding shapes, each at its own random
depth, the nearer to the camera painted over the farther. An image without a depth map (a picture, a procedural
image) is a picture on a ground plane: its top row at the near end of the depth range, its bottom row at the far
end (the convention of `rgbd:photo`). Depth is relative here (0 .. 1 across the bench's depth range, 0 its near
end); `loss_planes` says where a scene's focal stack is taken. The bundled `rgbd:` scenes are never drawn here:
they are the held-out scenes.

Images become targets exactly as `benchctl generate` prepares them (`benchctl.targets.prepare_target`).
"""

from __future__ import annotations

import argparse
import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from benchctl.errors import BadValueError, BenchctlError
from benchctl.targets import load_target, photo_specs

PROCEDURAL_PREFIX = "procedural:"
SCENES_PREFIX = "procedural-rgbd:"
PHOTOS_PREFIX = "photos:"
JOIN = "+"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
MAX_PROCEDURAL = 1_000_000  # a million distinct images: more than any run here trains on, and a list that fits
MAX_VALIDATION = 256  # images validated after every epoch, whatever the fraction: validation must not dwarf training
PROCEDURAL_SEED = 20240607  # fixed: procedural image i is the same picture in every install and version
SCENES_SEED = 20261126  # fixed likewise for procedural scene i


@dataclass(frozen=True)
class ImageSource:
    """One training image: a file (or a `photo:<name>` target), or procedural image (or, `scene`, procedural
    scene) number `index`."""

    name: str
    path: Path | str | None = None
    index: int | None = None
    scene: bool = False

    def load(self, size: tuple[int, int]) -> np.ndarray:
        """The image as float32 (H, W, 3) sRGB in [0, 1]; files keep their resolution, procedural ones are
        drawn at `size` (prepare_target resizes either to the ROI)."""
        return self.load_scene(size)[0] if self.scene else self._picture(size)

    def _picture(self, size: tuple[int, int]) -> np.ndarray:
        if self.path is not None:
            return load_target(self.path, size)
        assert self.index is not None
        return procedural_image(self.index, size)

    def load_scene(self, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The image and its relative depth (H, W) float64 in [0, 1] (0: the near end of the depth range): a
        procedural scene's own, else the picture on a ground plane (top row 0, bottom row 1)."""
        if self.scene:
            assert self.index is not None
            return procedural_scene(self.index, size)
        srgb = self._picture(size)
        rows, cols = srgb.shape[:2]
        return srgb, np.repeat(np.linspace(0.0, 1.0, rows)[:, None], cols, axis=1)


def _procedural_range(spec: str, prefix: str, scene: bool) -> list[ImageSource]:
    """`prefix`N (items 0 to N-1) or `prefix`A-B (items A to B)."""
    text = spec[len(prefix):]
    first, dash, last = text.partition("-")
    if not dash:  # N: items 0 to N-1
        first, last = "0", str(int(first) - 1) if first.isdigit() else ""
    if not (first.isdigit() and last.isdigit() and int(first) <= int(last) < int(first) + MAX_PROCEDURAL):
        items = "scenes" if scene else "images"
        raise BadValueError(f"--data {spec!r}: expected {prefix}N with 1 <= N <= {MAX_PROCEDURAL:,} {items} ({items} "
                            f"0 to N-1), or {prefix}A-B ({items} A to B, e.g. 200000-200031, {items} that a run on "
                            f"{prefix}N with N <= 200000 never sees), e.g. {prefix}64")
    stem = prefix[:-1]
    return [ImageSource(f"{stem}-{i:05d}", index=i, scene=scene) for i in range(int(first), int(last) + 1)]


def image_sources(spec: str) -> list[ImageSource]:
    """The images `--data` names: `procedural:N` or `procedural:A-B`, `procedural-rgbd:N` or `procedural-rgbd:A-B`
    (scenes with depth), `photos:train|eval`, a folder of image files (sorted by name), or several joined with "+"."""
    if JOIN in spec:
        parts = spec.split(JOIN)
        if not all(parts):
            raise BadValueError(f"--data {spec!r}: an empty part between '+' (e.g. procedural:64+photos:train)")
        return [source for part in parts for source in image_sources(part)]
    if spec.startswith(PHOTOS_PREFIX):
        split = spec[len(PHOTOS_PREFIX):]
        if split not in ("train", "eval"):
            raise BadValueError(f"--data {spec!r}: expected photos:train or photos:eval")
        return [ImageSource(name, path=name) for name in photo_specs(split)]
    for prefix, scene in ((PROCEDURAL_PREFIX, False), (SCENES_PREFIX, True)):
        if spec.startswith(prefix):
            return _procedural_range(spec, prefix, scene)
    folder = Path(spec)
    if not folder.is_dir():
        raise BenchctlError(f"--data {spec}: no such folder (give a folder of images, or procedural:N)")
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise BenchctlError(f"--data {spec}: no image files ({', '.join(IMAGE_SUFFIXES)}) in this folder")
    return [ImageSource(p.name, path=p) for p in files]


def split_sources(sources: Sequence[ImageSource], val_fraction: float,
                  seed: int) -> tuple[list[ImageSource], list[ImageSource]]:
    """(training, validation): a seeded random `val_fraction` of the images is held out for validation.

    At least one image is held out when the fraction is > 0 and there are two or more images, at most
    MAX_VALIDATION; at least one is always left for training.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise BadValueError(f"--val-fraction must be in [0, 1), got {val_fraction}")
    n = len(sources)
    n_val = min(n - 1, MAX_VALIDATION, max(1 if val_fraction > 0 else 0, round(n * val_fraction)))
    order = np.random.default_rng(seed).permutation(n)
    held_out = set(order[:n_val].tolist())
    return ([s for i, s in enumerate(sources) if i not in held_out],
            [s for i, s in enumerate(sources) if i in held_out])


def describe_sources(spec: str, train: Sequence[ImageSource], val: Sequence[ImageSource]) -> dict[str, object]:
    """What the data was, for a checkpoint: the spec, the counts, the held-out names and a digest of the
    training names (enough to tell whether another run used the same images)."""
    digest = hashlib.sha256("\n".join(s.name for s in train).encode()).hexdigest()[:16]
    kinds = ["procedural" if p.startswith(PROCEDURAL_PREFIX) else "procedural-rgbd" if p.startswith(SCENES_PREFIX)
             else "photos" if p.startswith(PHOTOS_PREFIX) else "folder" for p in spec.split(JOIN)]
    return {"spec": spec, "kind": "+".join(dict.fromkeys(kinds)),
            "train_images": len(train), "val_images": len(val), "val_names": [s.name for s in val],
            "train_names_sha256": digest}


def _gradient(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A linear colour gradient between two random colours in a random direction."""
    angle = rng.uniform(0, 2 * math.pi)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    t = (np.cos(angle) * x / max(w - 1, 1) + np.sin(angle) * y / max(h - 1, 1))
    t = (t - t.min()) / max(float(t.max() - t.min()), 1e-6)
    start, end = rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)
    return (start + t[..., None] * (end - start)).astype(np.float32)


def _shape_mask(rng: np.random.Generator, h: int, w: int, radius: float) -> tuple[np.ndarray, tuple[slice, slice]]:
    """An antialiased mask (float32 in [0, 1]) of a random disc, ellipse or polygon, cut to its bounding box."""
    cy, cx = rng.uniform(-radius, h + radius), rng.uniform(-radius, w + radius)
    top, left = max(0, int(cy - radius) - 2), max(0, int(cx - radius) - 2)
    bottom, right = min(h, int(cy + radius) + 3), min(w, int(cx + radius) + 3)
    if bottom <= top or right <= left:
        return np.zeros((0, 0), np.float32), (slice(0, 0), slice(0, 0))
    canvas = np.zeros((bottom - top, right - left), np.uint8)
    shift = 4  # sub-pixel coordinates for cv2's antialiased drawing
    centre = (round((cx - left) * 2**shift), round((cy - top) * 2**shift))
    kind = rng.integers(3)
    if kind == 0:
        cv2.circle(canvas, centre, round(radius * 2**shift), 255, -1, cv2.LINE_AA, shift)
    elif kind == 1:
        axes = (round(radius * 2**shift), round(radius * rng.uniform(0.2, 1.0) * 2**shift))
        cv2.ellipse(canvas, centre, axes, rng.uniform(0, 180), 0, 360, 255, -1, cv2.LINE_AA, shift)
    else:
        corners = int(rng.integers(3, 7))
        angles = np.sort(rng.uniform(0, 2 * math.pi, corners))
        radii = radius * rng.uniform(0.5, 1.0, corners)
        points = np.stack([centre[0] + radii * np.cos(angles) * 2**shift,
                           centre[1] + radii * np.sin(angles) * 2**shift], axis=1).round().astype(np.int32)
        cv2.fillPoly(canvas, [points], 255, cv2.LINE_AA, shift)
    return canvas.astype(np.float32) / 255.0, (slice(top, bottom), slice(left, right))


def procedural_image(index: int, size: tuple[int, int]) -> np.ndarray:
    """Procedural training image number `index` as float32 (H, W, 3) sRGB in [0, 1], drawn at `size`."""
    h, w = size
    if h < 1 or w < 1:
        raise ValueError(f"image size must be positive, got {size!r}")
    rng = np.random.default_rng([PROCEDURAL_SEED, index])
    dark = rng.uniform() < 0.3
    image = np.zeros((h, w, 3), np.float32) if dark else _gradient(rng, h, w)
    scale = min(h, w)
    r_min, r_max = max(1.0, 0.008 * scale), 0.3 * scale
    count = int(rng.integers(40, 120) if dark else rng.integers(150, 400))
    # Radii from a power law p(r) ~ r^-2 cut at r_max: as many leaves per octave of area as the image can
    # hold, so edges come at every scale and the leaves still cover most of the picture.
    radii = np.sort(np.minimum(r_max, r_min / (1 - rng.uniform(0, 1, count))))[::-1]
    for radius in radii:  # large leaves first, so small ones land on top and stay visible
        mask, (rows, cols) = _shape_mask(rng, h, w, float(radius))
        if mask.size == 0:
            continue
        colour = rng.uniform(0, 1, 3).astype(np.float32)
        fill = np.broadcast_to(colour, (*mask.shape, 3))
        if rng.uniform() < 0.15:  # a striped leaf: fine periodic detail at a random angle
            period = rng.uniform(2.5, 12.0)
            angle = rng.uniform(0, math.pi)
            y, x = np.mgrid[rows, cols].astype(np.float32)
            stripes = 0.5 + 0.5 * np.sin(2 * math.pi * (x * math.cos(angle) + y * math.sin(angle)) / period)
            fill = fill * stripes[..., None]
        region = image[rows, cols]
        region += mask[..., None] * (fill - region)
    if rng.uniform() < 0.3:  # a line of text: thin strokes and sharp corners
        text = "".join(rng.choice(list("ABCDEFGHJKLMNPQRSTUVWXYZ0123456789 "), int(rng.integers(6, 16))))
        canvas = np.zeros((h, w), np.uint8)
        font_scale = scale / 300 * rng.uniform(0.5, 1.5)
        origin = (int(rng.uniform(0, 0.5) * w), int(rng.uniform(0.2, 0.9) * h))
        cv2.putText(canvas, text, origin, cv2.FONT_HERSHEY_SIMPLEX, font_scale, 255,
                    max(1, round(font_scale * 2)), cv2.LINE_AA)
        alpha = canvas.astype(np.float32)[..., None] / 255.0
        image += alpha * (rng.uniform(0, 1, 3).astype(np.float32) - image)
    return np.clip(image, 0.0, 1.0)


def _background_depth(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """The relative depth of a scene's background: a fronto-parallel plane, a plane tilted in a random direction
    or a ground plane (depth growing down the picture), over a random part of the far half of the range."""
    kind = rng.integers(3)
    start = rng.uniform(0.0, 0.5)
    if kind == 0:
        return np.full((h, w), start)
    span = rng.uniform(0.2, 1.0 - start)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    if kind == 1:
        angle = rng.uniform(0, 2 * math.pi)
        ramp = np.cos(angle) * x / max(w - 1, 1) + np.sin(angle) * y / max(h - 1, 1)
    else:
        ramp = y / max(h - 1, 1)
    ramp = (ramp - ramp.min()) / max(float(ramp.max() - ramp.min()), 1e-9)
    return start + span * ramp


def procedural_scene(index: int, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Procedural scene number `index` at `size`: sRGB float32 (H, W, 3) in [0, 1] and relative depth float64
    (H, W) in [0, 1] (0: the near end of the depth range, nearest the SLM, farthest from the camera).

    A procedural picture on a background plane (`_background_depth`), then 1-4 shapes (discs, ellipses, polygons
    of 8-35 % of the short side) each textured with another procedural picture at its own depth, drawn from the
    farthest from the camera to the nearest, each shown only where nothing nearer the camera is (occlusion); a
    shape's depth holds where it covers more than half a pixel (depth has no antialiasing: no pixel lies between
    two layers)."""
    h, w = size
    if h < 1 or w < 1:
        raise ValueError(f"scene size must be positive, got {size!r}")
    rng = np.random.default_rng([SCENES_SEED, index])

    def texture() -> np.ndarray:
        return procedural_image(int(rng.integers(MAX_PROCEDURAL)), size)

    image = texture().copy()
    depth = _background_depth(rng, h, w)
    shapes = int(rng.integers(1, 5))
    for z in np.sort(rng.uniform(float(depth.min()), 1.0, shapes)):
        radius = rng.uniform(0.08, 0.35) * min(h, w)
        mask, (rows, cols) = _shape_mask(rng, h, w, float(radius))
        if mask.size == 0:
            continue
        fill = texture()[rows, cols]
        visible = mask * (depth[rows, cols] <= z)  # a tilted background may pass in front of the shape
        region = image[rows, cols]
        region += visible[..., None] * (fill - region)
        depth[rows, cols] = np.where(visible > 0.5, z, depth[rows, cols])
    return np.clip(image, 0.0, 1.0), depth


def loss_planes(depth: np.ndarray, count: int, jitter: float = 0.0) -> tuple[float, ...]:
    """Where to take the focal stack of a scene whose depth map is `depth` (any unit): its distinct depths when
    it has at most `count` (a layered scene: every layer in focus on its own plane), else `count` planes evenly
    spread over its depth span, each at the centre of its bin moved by `jitter` (-0.5 .. 0.5) bins (training moves
    them at random, so every depth is in focus on some plane over the steps)."""
    if count < 1:
        raise ValueError(f"a focal stack needs at least one plane, got {count}")
    if not -0.5 <= jitter <= 0.5:
        raise ValueError(f"jitter must lie in [-0.5, 0.5] bins, got {jitter}")
    distinct = np.unique(depth)
    if len(distinct) <= count:
        return tuple(float(z) for z in distinct)
    low, high = float(distinct[0]), float(distinct[-1])
    return tuple(low + (k + 0.5 + jitter) * (high - low) / count for k in range(count))


def write_procedural(out_dir: Path, count: int, size: tuple[int, int]) -> list[Path]:
    """Write procedural images 0 .. count - 1 as 8-bit PNGs named like their `procedural:N` sources."""
    from benchctl.files import ensure_dir
    from benchctl.images import write_png

    ensure_dir(out_dir)
    return [write_png(out_dir / f"{source.name}.png", (procedural_image(source.index, size) * 255).round()
                      .astype(np.uint8))
            for source in image_sources(f"{PROCEDURAL_PREFIX}{count}") if source.index is not None]


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m benchctl.training.data OUTDIR --count N --size HxW`: write the procedural images as PNGs."""
    parser = argparse.ArgumentParser(prog="python -m benchctl.training.data",
                                     description="Write benchctl's procedural training images as PNG files.")
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--count", type=int, default=16)
    parser.add_argument("--size", default="880x1600", help="rows x cols (default: the simulated bench's ROI)")
    args = parser.parse_args(argv)
    rows, cols = (int(v) for v in args.size.lower().split("x"))
    for path in write_procedural(args.out_dir, args.count, (rows, cols)):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
