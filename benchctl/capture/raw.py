"""Decoding RAW frames (Canon CR2/CR3, DNG, anything LibRaw reads) to linear sensor data.

Scores compare light intensities, so every frame is used as linear signal: black level subtracted per CFA
position, divided by (white - black), no white balance, no brightness or gamma curve, no colour matrix.
`decode_raw` reads the Bayer mosaic without LibRaw's processing; the colour layout comes from the file
(`raw_pattern` + `color_desc`), never from an assumption about the camera. A monochrome sensor's frame (a
LinearRaw DNG with one sample per pixel, as a Mono8..16 machine-vision camera gives) has no colour layout: every
pixel records whichever colour lights it, so its cells are all MONO and every colour's plane is read from all of
them (a colour capture exposes one colour at a time).

LibRaw traps this module avoids (verified with rawpy 0.28 / LibRaw 0.22):
- `raw_image_visible` is a view into LibRaw's memory: everything is computed before the file is closed.
- `raw_pattern` is relative to the full sensor (margins included); the visible image's layout is shifted by
  the margins.
- `postprocess()` defaults are not linear: `adjust_maximum_thr=0.75` rescales a frame whose maximum is above
  75 % of the white level by that maximum (a gain that changes from frame to frame), and without `user_wb`
  LibRaw multiplies the channels by its daylight balance (derived from the file's colour matrix, so it
  depends on the camera). `linear_rgb` sets every option that matters.
- A monochrome DNG comes back with `num_colors` 1, a 1x1 `raw_pattern` ([[6]]) and `color_desc` "GMCY", which
  mean nothing there; its one black level is repeated in `black_level_per_channel`, and `postprocess()` returns
  one channel. `num_colors` is what tells it from a CFA file that lost its CFAPattern (LibRaw then invents a
  3-colour pattern, refused below).
"""

from __future__ import annotations

import io
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np
import rawpy

from benchctl.dng import CFA, LINEAR_RAW, full_size_images
from benchctl.errors import BadValueError, BenchctlError

_CELLS = ((0, 0), (0, 1), (1, 0), (1, 1))
MONO = 3
"""`RawImage.cfa` code of a monochrome sensor's pixel: it records every colour (the colour exposed decides which)."""
_BAYER_TO_RGB = {  # OpenCV names a pattern by the second row's 2nd and 3rd pixels: RGGB is "BG"
    "RGGB": cv2.COLOR_BayerBG2RGB,
    "BGGR": cv2.COLOR_BayerRG2RGB,
    "GRBG": cv2.COLOR_BayerGB2RGB,
    "GBRG": cv2.COLOR_BayerGR2RGB,
}


@dataclass(frozen=True, eq=False)
class RawImage:
    """A decoded frame: the visible Bayer (or monochrome) mosaic as linear signal (0 = black, 1 = white level).

    mosaic: float32 (H, W), (raw - black) / (white - black) per CFA position; noise below black stays negative.
    cfa: (2, 2) colour of each CFA position at the top-left of the mosaic, 0 = R, 1 = G, 2 = B; MONO in every
    cell for a monochrome sensor.
    saturated: bool (H, W), raw value at or above the white level (or the camera's per-channel clip level).
    black_levels: float (2, 2) per CFA position, and white_level, in raw counts, as the file states them.
    source: the file the frame came from ('<bytes>' for data in memory), or how it was combined.
    """

    mosaic: np.ndarray
    cfa: np.ndarray
    saturated: np.ndarray
    black_levels: np.ndarray
    white_level: float
    source: str

    @property
    def monochrome(self) -> bool:
        """True for a monochrome sensor's frame (no colour filters)."""
        return bool((self.cfa == MONO).all())

    @property
    def layout(self) -> str:
        """The CFA layout name, e.g. 'RGGB', or 'mono'."""
        return "mono" if self.monochrome else "".join("RGB"[c] for c in self.cfa.flat)

    @property
    def saturation_fraction(self) -> float:
        """Fraction of pixels at the clip level: a frame with many is over-exposed and reads low."""
        return float(self.saturated.mean())

    def planes(self) -> np.ndarray:
        """(3, H/2, W/2) float32: R, mean of the two Gs, B, each from its own CFA position (no interpolation);
        monochrome: each the mean of the 2x2 cell."""
        rows, cols = (n - n % 2 for n in self.mosaic.shape)
        cells = [self.mosaic[i:rows:2, j:cols:2] for i, j in _CELLS]
        return np.stack([np.mean([cell for cell, c in zip(cells, self.cfa.flat) if c in (colour, MONO)], axis=0)
                         for colour in range(3)]).astype(np.float32)

    def demosaic(self) -> np.ndarray:
        """(H, W, 3) float32 linear RGB by OpenCV's bilinear Bayer interpolation, full resolution.

        OpenCV demosaics integers, so the mosaic is mapped affinely onto 0..65535 (covering its full range,
        negatives included) and back; bilinear interpolation commutes with that map, so only the
        quantisation step (range / 65535) is added. Monochrome: the mosaic itself in all three channels.
        """
        if self.monochrome:
            return np.repeat(self.mosaic[:, :, None], 3, axis=2)
        low = min(0.0, float(self.mosaic.min()))
        high = max(1.0, float(self.mosaic.max()))
        scale = 65535.0 / (high - low)
        counts = np.rint((self.mosaic - low) * scale).astype(np.uint16)
        rgb = cv2.cvtColor(counts, _BAYER_TO_RGB[self.layout])
        return rgb.astype(np.float32) / np.float32(scale) + np.float32(low)


@contextmanager
def _opened(source: Path | str | bytes) -> Iterator[tuple[rawpy.RawPy, str]]:
    """The open rawpy file and its name; LibRaw errors (also the lazy ones while unpacking) become one line."""
    target: str | io.BytesIO
    if isinstance(source, (bytes, bytearray)):
        name, target = "<bytes>", io.BytesIO(source)
    else:
        name = target = str(source)
        if not Path(source).exists():
            raise BenchctlError(f"RAW file {name} does not exist")
        if not Path(source).is_file():
            raise BenchctlError(f"RAW file {name} is not a file")
    try:
        with rawpy.imread(target) as raw:
            yield raw, name
    except rawpy.LibRawError as exc:
        raise BenchctlError(f"cannot decode RAW file {name}: {_reason(exc)}") from None


def _reason(exc: Exception) -> str:
    if isinstance(exc, rawpy.LibRawFileUnsupportedError):
        return "not a RAW file LibRaw can read (unsupported format, or a damaged / truncated header)"
    if isinstance(exc, rawpy.LibRawIOError):
        return "read error (file truncated or unreadable)"
    detail = exc.args[0] if exc.args else exc
    return detail.decode(errors="replace") if isinstance(detail, bytes) else str(detail)


def decode_raw(source: Path | str | bytes) -> RawImage:
    """Decode a RAW file (a path, or its bytes) to a linear `RawImage` of the visible sensor area."""
    with _opened(source) as (raw, name):
        cfa, index = _layout(raw, name, source)
        per_channel = raw.black_level_per_channel
        black = np.array([per_channel[i] for i in index.flat], dtype=np.float64).reshape(2, 2)
        white = float(raw.white_level)
        if not (black < white).all():
            raise BenchctlError(f"{name}: white level {white:g} is not above the black levels {black.ravel()}")
        camera_clip = raw.camera_white_level_per_channel
        clip = [min(white, camera_clip[i]) if camera_clip else white for i in index.flat]

        visible = raw.raw_image_visible  # a view into LibRaw's buffer: used only inside this block
        mosaic = np.empty(visible.shape, dtype=np.float32)
        saturated = np.empty(visible.shape, dtype=bool)
        for (i, j), level in zip(_CELLS, clip):
            counts = visible[i::2, j::2]
            mosaic[i::2, j::2] = (counts.astype(np.float32) - np.float32(black[i, j])) / np.float32(white - black[i, j])
            saturated[i::2, j::2] = counts >= level
    return RawImage(mosaic, cfa, saturated, black, white, name)


def _layout(raw: rawpy.RawPy, name: str, source: Path | str | bytes) -> tuple[np.ndarray, np.ndarray]:
    """(cfa, index): the colour of each 2x2 cell at the visible origin (MONO everywhere for a monochrome sensor)
    and LibRaw's channel index there (for the per-channel black and clip levels)."""
    if raw.num_colors == 1:  # one colour: a monochrome sensor (one black level, channel 0) if the file says so
        with io.BytesIO(source) if isinstance(source, (bytes, bytearray)) else open(source, "rb") as stream:
            images = full_size_images(stream)
        if (LINEAR_RAW, 1) not in images or any(kind == CFA for kind, _ in images):
            raise BenchctlError(f"{name}: LibRaw reads one colour, but the file declares no monochrome image "
                                f"(PhotometricInterpretation, samples: {images or 'none'}); a CFA file without "
                                "its CFAPattern tag?")
        return np.full((2, 2), MONO, dtype=np.uint8), np.zeros((2, 2), dtype=np.intp)
    try:
        pattern = raw.raw_pattern
    except NotImplementedError:  # a LibRaw `filters` code rawpy has no pattern for (e.g. DNG without CFA tag)
        pattern = None
    if pattern is None or pattern.shape != (2, 2):
        shape = "none" if pattern is None else "x".join(map(str, pattern.shape))
        raise BenchctlError(f"{name} is not a 2x2 Bayer RAW file (CFA pattern: {shape}; no CFA tag?)")
    sizes = raw.sizes
    index = np.roll(pattern, (-sizes.top_margin, -sizes.left_margin), axis=(0, 1))  # layout at visible origin
    desc = raw.color_desc.decode("ascii", "replace")
    letters = "".join(desc[i] if i < len(desc) else "?" for i in index.flat)
    if sorted(letters) != ["B", "G", "G", "R"]:
        raise BenchctlError(f"{name}: CFA colours {letters} are not an RGB Bayer pattern")
    return np.array(["RGB".index(letter) for letter in letters], dtype=np.uint8).reshape(2, 2), index


def linear_rgb(source: Path | str | bytes, half_size: bool = False) -> np.ndarray:
    """(H, W, 3) float32 camera RGB from LibRaw's own demosaic, on the same linear scale as `RawImage.mosaic`.

    Uses the linear recipe (gamma 1, no auto-brightness, no white balance, raw colour space, no per-frame
    maximum adjustment). LibRaw clips to 0 .. white and rounds down to 16 bits (at most 1 / 65535 low).
    half_size: one pixel per 2x2 cell, the two greens averaged (fast, no interpolation). A monochrome frame
    (one channel from LibRaw, which does not halve it) is given in all three channels, its 2x2 cells averaged
    for half_size.
    """
    with _opened(source) as (raw, _):
        rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, user_wb=[1.0, 1.0, 1.0, 1.0],
                              output_color=rawpy.ColorSpace.raw, adjust_maximum_thr=0.0, half_size=half_size)
    linear = rgb.astype(np.float32) / np.float32(65535.0)
    if linear.shape[2] == 1:
        if half_size:
            rows, cols = (n // 2 for n in linear.shape[:2])
            linear = linear[:2 * rows, :2 * cols].reshape(rows, 2, cols, 2, 1).mean(axis=(1, 3))
        linear = np.repeat(linear, 3, axis=2)
    return linear


def _check_same_grid(reference: RawImage, other: RawImage, action: str) -> None:
    if other.mosaic.shape != reference.mosaic.shape or not np.array_equal(other.cfa, reference.cfa):
        raise BadValueError(
            f"cannot {action} {other.source} ({'x'.join(map(str, other.mosaic.shape))} {other.layout}) with "
            f"{reference.source} ({'x'.join(map(str, reference.mosaic.shape))} {reference.layout})")


def average_frames(images: Iterable[RawImage]) -> RawImage:
    """Mean of N frames of one scene (noise / sqrt(N)); a pixel saturated in any frame stays flagged.

    Streaming: `images` may be a generator that decodes each frame as it is asked for, and each is added to a
    running sum and let go, so N frames need the memory of one (plus the sum), not of N. black_levels and white_level
    are the frames' means (information only: each mosaic is already scaled).
    """
    frames = iter(images)
    first = next(frames, None)
    if first is None:
        raise BadValueError("average_frames needs at least one frame")
    total: np.ndarray | None = None  # the mean of one frame is that frame: no float64 copy of a sensor-sized mosaic
    saturated = first.saturated
    black_levels, white_level = first.black_levels.astype(np.float64), first.white_level
    count, last = 1, first.source
    for image in frames:
        _check_same_grid(first, image, "average")
        if total is None:
            total, saturated = first.mosaic.astype(np.float64), first.saturated.copy()
        total += image.mosaic
        saturated |= image.saturated
        black_levels = black_levels + image.black_levels
        white_level += image.white_level
        count, last = count + 1, image.source
        del image  # let it go before the next one is decoded
    if total is None:
        return first
    total /= count
    return RawImage(
        mosaic=total.astype(np.float32),
        cfa=first.cfa.copy(),
        saturated=saturated,
        black_levels=black_levels / count,
        white_level=white_level / count,
        source=f"mean of {count} frames ({first.source} .. {last})",
    )


def subtract_dark(image: RawImage, dark: RawImage) -> RawImage:
    """`image` minus a dark frame (same exposure, light off): removes dark current and fixed-pattern offsets.

    The result keeps its sign (no clipping at 0), so the mean of a dark-subtracted background is unbiased
    noise around 0; clip only where a display needs it. A pixel saturated in either frame stays flagged.
    """
    _check_same_grid(image, dark, "subtract dark frame")
    return RawImage(
        mosaic=image.mosaic - dark.mosaic,
        cfa=image.cfa.copy(),
        saturated=image.saturated | dark.saturated,
        black_levels=image.black_levels,
        white_level=image.white_level,
        source=f"{image.source} minus dark {dark.source}",
    )
