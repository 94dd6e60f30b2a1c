"""Image files: reading the formats benchctl accepts (in RGB order) and writing PNGs atomically.

OpenCV stores colour as BGR(A); this module is the only place that knows, so the rest of benchctl sees RGB.
Files go through bytes (imdecode / imencode), which also handles paths OpenCV's own file I/O cannot.
Only APIs common to OpenCV 4.x and 5.x are used.

Nothing is decoded before its size is known: OpenCV decodes up to 2^30 pixels, so a few megabytes of compressed
file could ask for gigabytes. The accepted formats are the ones whose header gives the size (`header_size`: PNG,
JPEG, BMP, TIFF and BigTIFF, WebP); anything else OpenCV would decode is refused unread.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from benchctl.errors import BenchctlError
from benchctl.files import IMAGE_BYTES, atomic_write_bytes, read_capped
from benchctl.limits import check_pixels

_SWAP_RB = [2, 1, 0, 3]  # BGR(A) <-> RGB(A) channel order; the same permutation both ways
ACCEPTED = "PNG, JPEG, BMP, TIFF or WebP"
# JPEG markers: start of frame (the image size) and those that stand alone (no length follows)
_SOF = {*range(0xC0, 0xD0)} - {0xC4, 0xC8, 0xCC}
_STANDALONE = {0x01, *range(0xD0, 0xD9)}
_TIFF_WIDTH, _TIFF_HEIGHT = 256, 257


def read_image(path: str | Path) -> np.ndarray:
    """Decode an image file as stored: dtype kept, (H, W) gray or (H, W, 3|4) in RGB(A) order. Its size is read
    from its header and checked against the pixel limit before anything is decoded."""
    path = Path(path)
    try:
        data = read_capped(path, "image", IMAGE_BYTES)
    except FileNotFoundError as exc:
        raise BenchctlError(f"{path}: cannot read image: {exc.strerror or exc}") from None
    if not data:
        raise BenchctlError(f"{path}: empty file (0 bytes), not an image")
    kind = image_format(data)
    if kind is None:
        raise BenchctlError(f"{path}: not a {ACCEPTED} image")
    size = header_size(data)
    if size is None:
        raise BenchctlError(f"{path}: a {kind} file whose header gives no image size; not decoded")
    check_pixels(str(path), *size)
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise BenchctlError(f"{path}: not an image OpenCV can decode ({kind} header, damaged data)")
    if image.shape[:2] != size:
        raise BenchctlError(f"{path}: decoded as {image.shape[0]} x {image.shape[1]} pixels, its header says "
                            f"{size[0]} x {size[1]}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3:
        image = image[:, :, _SWAP_RB[: image.shape[2]]]
    return image


def image_format(data: bytes) -> str | None:
    """The accepted format `data` starts like ("PNG", "JPEG", "BMP", "TIFF", "WebP"), or None."""
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "PNG"
    if data.startswith(b"\xff\xd8"):
        return "JPEG"
    if data.startswith(b"BM"):
        return "BMP"
    if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "TIFF"
    if data.startswith(b"RIFF") and data[8:12] == b"WEBP":
        return "WebP"
    return None


def header_size(data: bytes) -> tuple[int, int] | None:
    """(height, width) from the header of an accepted format, read before decoding; None for any other format
    or a header that does not give a size (zero, or cut short)."""
    readers = {"PNG": _png_size, "JPEG": _jpeg_size, "BMP": _bmp_size, "TIFF": _tiff_size, "WebP": _webp_size}
    kind = image_format(data)
    size = readers[kind](data) if kind is not None else None
    return size if size is not None and size[0] > 0 and size[1] > 0 else None


def _png_size(data: bytes) -> tuple[int, int] | None:
    if data[12:16] != b"IHDR" or len(data) < 24:
        return None
    return int.from_bytes(data[20:24], "big"), int.from_bytes(data[16:20], "big")


def _bmp_size(data: bytes) -> tuple[int, int] | None:
    if len(data) < 26:
        return None
    if int.from_bytes(data[14:18], "little") == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sizes
        return int.from_bytes(data[20:22], "little"), int.from_bytes(data[18:20], "little")
    return abs(int.from_bytes(data[22:26], "little", signed=True)), int.from_bytes(data[18:22], "little", signed=True)


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """The size in the first start-of-frame marker, walking the segments (a thumbnail inside APP1 is skipped)."""
    at = 2
    while at + 1 < len(data):
        if data[at] != 0xFF:
            return None
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker in _STANDALONE:
            at += 2
            continue
        if marker == 0xDA or at + 4 > len(data):  # scan data before any frame header: no size to read
            return None
        if marker in _SOF:
            if at + 9 > len(data):
                return None
            return int.from_bytes(data[at + 5:at + 7], "big"), int.from_bytes(data[at + 7:at + 9], "big")
        at += 2 + int.from_bytes(data[at + 2:at + 4], "big")
    return None


def _tiff_size(data: bytes) -> tuple[int, int] | None:
    """ImageLength and ImageWidth of the first image file directory (the page OpenCV decodes), TIFF or BigTIFF."""
    order: Literal["little", "big"] = "little" if data[:2] == b"II" else "big"

    def number(start: int, size: int) -> int:
        return int.from_bytes(data[start:start + size], order)

    big = number(2, 2) == 43
    offset_size, count_size, entry_size = (8, 8, 20) if big else (4, 2, 12)
    ifd = number(8, 8) if big else number(4, 4)
    if ifd + count_size > len(data):
        return None
    found: dict[int, int] = {}
    start = ifd + count_size
    for index in range(number(ifd, count_size)):
        entry = start + index * entry_size
        if entry + entry_size > len(data):
            return None
        tag, kind = number(entry, 2), number(entry + 2, 2)
        if tag in (_TIFF_WIDTH, _TIFF_HEIGHT):
            value = entry + 4 + offset_size  # the value sits in the entry: one SHORT, LONG or LONG8
            sizes = {3: 2, 4: 4, 16: 8}
            if kind not in sizes:
                return None
            found[tag] = number(value, sizes[kind])
    if _TIFF_WIDTH not in found or _TIFF_HEIGHT not in found:
        return None
    return found[_TIFF_HEIGHT], found[_TIFF_WIDTH]


def _webp_size(data: bytes) -> tuple[int, int] | None:
    chunk, body = data[12:16], 20
    if chunk == b"VP8 " and len(data) >= body + 10 and data[body + 3:body + 6] == b"\x9d\x01\x2a":
        width, height = (int.from_bytes(data[at:at + 2], "little") & 0x3FFF for at in (body + 6, body + 8))
        return height, width
    if chunk == b"VP8L" and len(data) >= body + 5 and data[body] == 0x2F:
        bits = int.from_bytes(data[body + 1:body + 5], "little")
        return ((bits >> 14) & 0x3FFF) + 1, (bits & 0x3FFF) + 1
    if chunk == b"VP8X" and len(data) >= body + 10:
        width, height = (int.from_bytes(data[at:at + 3], "little") + 1 for at in (body + 4, body + 7))
        return height, width
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
