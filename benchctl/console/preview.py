"""From a camera's live-view frame to what the page shows: demosaiced linear RGB, statistics, the display image.

A frame is a RAW file (decoded like any capture: black level removed, scaled to the white level, saturated pixels
flagged, and the bins a binned readout says hold a saturated sensor pixel) or a body's JPEG (sRGB: decoded to linear
light through the one sRGB conversion; 255 counts as saturated). Statistics are taken in linear light as fractions
of full scale: a histogram per colour channel, peak, mean and the share of saturated pixels. The display image is
scaled to fit the page, shown linear or gamma-encoded (sRGB), with saturated pixels painted magenta, and sent as
JPEG.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Literal

import cv2
import numpy as np
import torch

from benchctl.capture.raw import RawImage, decode_raw
from benchctl.devices.camera.base import RAW_FORMATS, PreviewFrame, Window
from benchctl.errors import BenchctlError
from benchctl.optics.colour import linear_to_srgb, srgb_to_linear

DISPLAY_SIZE = (640, 960)  # (rows, cols) the page's preview is at most
ZOOM_SIZE = 256  # sensor pixels across the 1:1 zoom
HISTOGRAM_BINS = 64
SATURATED_RGB = (255, 0, 255)
JPEG_QUALITY = 85
Mode = Literal["gamma", "linear"]

_LEVELS = 4096  # linear -> 8-bit display tables: linear values quantised to 1/4096 of full scale
_GAMMA_TABLE = (linear_to_srgb(torch.linspace(0, 1, _LEVELS, dtype=torch.float64)).clamp(0, 1) * 255).round().to(
    torch.uint8).numpy()
_LINEAR_TABLE = np.round(np.linspace(0, 255, _LEVELS)).astype(np.uint8)
_FROM_SRGB8 = srgb_to_linear(torch.arange(256, dtype=torch.float64) / 255).numpy().astype(np.float32)


@dataclass
class Linear:
    """A frame in linear light: (rows, cols, 3) float32 as fractions of full scale, saturated pixels, and the part
    of the sensor's active area it shows (None: unknown, the whole frame)."""

    rgb: np.ndarray
    saturated: np.ndarray
    window: Window | None
    full_shape: tuple[int, int] | None


def decode(frame: PreviewFrame, max_cols: int = DISPLAY_SIZE[1]) -> Linear:
    """A live-view frame in linear light. A RAW mosaic more than twice `max_cols` wide is taken at half size (one
    pixel per CFA cell, no interpolation), else demosaiced at full size."""
    if frame.format == "jpeg":
        bgr = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise BenchctlError("camera live view: a frame is not a JPEG OpenCV can decode")
        rgb8 = np.ascontiguousarray(bgr[:, :, ::-1])
        return Linear(_FROM_SRGB8[rgb8], (rgb8 == 255).any(axis=2), frame.window, frame.full_shape)
    if frame.format not in RAW_FORMATS:
        raise BenchctlError(f"camera live view: frame format {frame.format!r} is neither JPEG nor RAW")
    raw = decode_raw(frame.data)
    full_shape = frame.full_shape or (tuple(raw.mosaic.shape) if frame.window is None else None)
    saturated = raw.saturated
    bins = frame.metadata.get("saturated_bins")  # a binned readout's own word on its bins (the simulated camera's)
    if bins is not None and np.shape(bins) == saturated.shape:
        saturated = saturated | bins
    return _from_raw(raw, saturated, max_cols, frame.window, full_shape)


def _from_raw(raw: RawImage, saturated: np.ndarray, max_cols: int, window: Window | None,
              full_shape: tuple[int, int] | None) -> Linear:
    if raw.mosaic.shape[1] > 2 * max_cols:
        rgb = np.moveaxis(raw.planes(), 0, 2)
        rows, cols = rgb.shape[:2]
        saturated = np.asarray(saturated[:2 * rows, :2 * cols].reshape(rows, 2, cols, 2).any(axis=(1, 3)))
    else:
        rgb = raw.demosaic()
    return Linear(np.ascontiguousarray(rgb, dtype=np.float32), saturated, window, full_shape)


def crop(image: Linear, window: Window) -> Linear:
    """The part of `image` that shows `window` of the active area, at the image's own resolution."""
    top, left, rows, cols = _frame_window(image)
    full_rows, full_cols = image.rgb.shape[:2]
    scale_y, scale_x = full_rows / rows, full_cols / cols
    r0, c0 = int((window[0] - top) * scale_y), int((window[1] - left) * scale_x)
    r1, c1 = int(r0 + window[2] * scale_y), int(c0 + window[3] * scale_x)
    r0, c0 = max(0, min(r0, full_rows - 1)), max(0, min(c0, full_cols - 1))
    r1, c1 = max(r0 + 1, min(r1, full_rows)), max(c0 + 1, min(c1, full_cols))
    return Linear(image.rgb[r0:r1, c0:c1], image.saturated[r0:r1, c0:c1], window, image.full_shape)


def _frame_window(image: Linear) -> Window:
    if image.window is not None:
        return image.window
    rows, cols = image.full_shape or image.rgb.shape[:2]
    return 0, 0, rows, cols


def zoom_window(shape: tuple[int, int], centre: tuple[float, float], size: int = ZOOM_SIZE) -> Window:
    """The `size` x `size` window of a frame of `shape` (rows, cols: the active area's, or the frame's own where
    that is unknown) around `centre` (x, y as fractions of the frame), inside it, its corner on a CFA cell."""
    rows, cols = shape
    size_y, size_x = min(size, rows), min(size, cols)
    top = int(min(max(0.0, centre[1] * rows - size_y / 2), rows - size_y))
    left = int(min(max(0.0, centre[0] * cols - size_x / 2), cols - size_x))
    return top & ~1, left & ~1, size_y, size_x


def statistics(image: Linear) -> dict[str, Any]:
    """Per channel (R, G, B) the histogram of linear signal over 0..1 of full scale (HISTOGRAM_BINS bins, values
    beyond counted in the end bins), peak and mean as fractions of full scale; the share of saturated pixels."""
    stats: dict[str, Any] = {"histogram": [], "peak": [], "mean": []}
    bins = np.clip((image.rgb * HISTOGRAM_BINS).astype(np.int32), 0, HISTOGRAM_BINS - 1)
    for channel in range(3):
        stats["histogram"].append(np.bincount(bins[:, :, channel].ravel(), minlength=HISTOGRAM_BINS).tolist())
        stats["peak"].append(round(float(image.rgb[:, :, channel].max()), 5))
        stats["mean"].append(round(float(image.rgb[:, :, channel].mean()), 6))
    stats["saturated"] = round(float(image.saturated.mean()), 6)
    return stats


def display_jpeg(image: Linear, mode: Mode, size: tuple[int, int] | None = DISPLAY_SIZE) -> bytes:
    """The image scaled to fit `size` (rows, cols; None: as it is), linear or sRGB, saturated pixels magenta."""
    rgb, saturated = image.rgb, image.saturated
    if size is not None:
        scale = min(size[0] / rgb.shape[0], size[1] / rgb.shape[1], 1.0)
        if scale < 1.0:
            shape = (max(1, round(rgb.shape[1] * scale)), max(1, round(rgb.shape[0] * scale)))
            rgb = cv2.resize(rgb, shape, interpolation=cv2.INTER_AREA)
            saturated = cv2.resize(saturated.astype(np.uint8), shape, interpolation=cv2.INTER_AREA) > 0
    levels = np.clip(rgb * (_LEVELS - 1) + 0.5, 0, _LEVELS - 1).astype(np.int32)
    shown = (_GAMMA_TABLE if mode == "gamma" else _LINEAR_TABLE)[levels]
    shown[saturated] = SATURATED_RGB
    bgr = np.ascontiguousarray(shown[:, :, ::-1])
    ok, encoded = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise BenchctlError("preview frame could not be encoded as JPEG")
    return encoded.tobytes()


@dataclass
class Shown:
    """One preview frame as the page gets it: JPEGs (the frame, and the 1:1 zoom when one is asked for) and a header
    with statistics, what the frame shows (SLM frame, lasers, where the device says) and timings."""

    seq: int
    jpeg: bytes
    zoom: bytes | None
    header: dict[str, Any]


def shown_frame(seq: int, frame: PreviewFrame, zoom: PreviewFrame | None, *, mode: Mode,
                zoom_centre: tuple[float, float] | None, render_started: float,
                render_s: tuple[float, float]) -> Shown:
    """Decode, measure and encode one frame (and its zoom: the camera's own 1:1 window when it has one, else the
    frame's crop at its own resolution). `render_s`: the seconds and CPU seconds the camera took for it; the
    header has both for rendering and encoding (CPU seconds: this thread's, what a free core would take)."""
    started, cpu = time.perf_counter(), time.thread_time()
    image = decode(frame)
    zoom_jpeg = None
    window = None
    if zoom_centre is not None:
        if zoom is not None:
            zoomed = decode(zoom, max_cols=ZOOM_SIZE)
            window = zoom.window
        else:
            window = zoom_window(image.full_shape or image.rgb.shape[:2], zoom_centre)
            zoomed = crop(image, window)
        zoom_jpeg = display_jpeg(zoomed, mode, size=None)
    jpeg = display_jpeg(image, mode)
    header = {
        "seq": seq, "format": frame.format, "shape": list(image.rgb.shape[:2]), "full_shape": image.full_shape,
        "zoom_window": window, "stats": statistics(image),
        "source": {key: frame.metadata[key] for key in ("slm_frame", "lasers_on_w", "coarse", "exposure_s", "iso",
                                                        "bin") if key in frame.metadata},
        "render_started": render_started, "render_s": round(render_s[0], 6), "render_cpu_s": round(render_s[1], 6),
        "encode_s": round(time.perf_counter() - started, 6), "encode_cpu_s": round(time.thread_time() - cpu, 6),
        "published": time.time(),
    }
    return Shown(seq, jpeg, zoom_jpeg, header)

