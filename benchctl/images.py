"""Image files: reading any format OpenCV decodes (in RGB order) and writing PNGs atomically.

OpenCV stores colour as BGR(A); this module is the only place that knows, so the rest of benchctl sees RGB.
Files go through bytes (imdecode / imencode), which also handles paths OpenCV's own file I/O cannot.
Only APIs common to OpenCV 4.x and 5.x are used.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from benchctl.errors import BenchctlError
from benchctl.files import IMAGE_BYTES, atomic_write_bytes, read_capped
from benchctl.limits import check_pixels

_SWAP_RB = [2, 1, 0, 3]  # BGR(A) <-> RGB(A) channel order; the same permutation both ways


def read_image(path: str | Path) -> np.ndarray:
    """Decode an image file as stored: dtype kept, (H, W) gray or (H, W, 3|4) in RGB(A) order."""
    path = Path(path)
    try:
        data = read_capped(path, "image", IMAGE_BYTES)
    except FileNotFoundError as exc:
        raise BenchctlError(f"{path}: cannot read image: {exc.strerror or exc}") from None
    if not data:
        raise BenchctlError(f"{path}: empty file (0 bytes), not an image")
    size = header_size(data)
    if size is not None:
        check_pixels(str(path), *size)
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is not None:
        check_pixels(str(path), *image.shape[:2])  # formats whose header is not read above
    if image is None:
        raise BenchctlError(f"{path}: not an image OpenCV can decode")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3:
        image = image[:, :, _SWAP_RB[: image.shape[2]]]
    return image


def header_size(data: bytes) -> tuple[int, int] | None:
    """(height, width) from a PNG, JPEG or BMP header, read before decoding (None for other formats or a
    header that does not parse: the decoder then judges the file)."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) >= 24:
        return int.from_bytes(data[20:24], "big"), int.from_bytes(data[16:20], "big")
    if data[:2] == b"BM" and len(data) >= 26:
        return abs(int.from_bytes(data[22:26], "little", signed=True)), int.from_bytes(data[18:22], "little")
    if data[:2] == b"\xff\xd8":
        at = 2
        while at + 9 <= len(data) and data[at] == 0xFF:
            marker, length = data[at + 1], int.from_bytes(data[at + 2:at + 4], "big")
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame: the image size
                return int.from_bytes(data[at + 5:at + 7], "big"), int.from_bytes(data[at + 7:at + 9], "big")
            at += 2 + length
    return None


def write_png(path: str | Path, array: np.ndarray) -> Path:
    """Write uint8 or uint16 (H, W) gray or (H, W, 3) RGB as PNG, atomically (see files.atomic_write_bytes).

    Returns the path written.
    """
    if array.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"PNG needs uint8 or uint16 pixels, got {array.dtype}")
    if not (array.ndim == 2 or (array.ndim == 3 and array.shape[2] == 3)):
        raise ValueError(f"PNG needs an (H, W) or (H, W, 3) array, got shape {array.shape}")
    if array.ndim == 3:
        array = array[:, :, _SWAP_RB[:3]]
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(array))
    if not ok:
        raise ValueError(f"OpenCV could not encode a {array.shape} {array.dtype} array as PNG")
    return atomic_write_bytes(Path(path), encoded.tobytes())
