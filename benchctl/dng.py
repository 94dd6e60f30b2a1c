"""Writing a Bayer (or monochrome) mosaic as a minimal DNG 1.4 file that LibRaw (rawpy) reads back bit-exactly,
and reading which kind of image a TIFF-based RAW file holds.

The simulated camera uses this so that the capture pipeline decodes its frames with the same code as a real
camera's. The file is the smallest layout LibRaw reads losslessly: a little-endian TIFF, the image as one
uncompressed strip of 16-bit samples, PhotometricInterpretation CFA, and always CFAPattern (without it LibRaw
0.22 makes up an arbitrary, run-dependent filter layout). Written with `struct`, no extra dependency. The
directory is written after the pixels, so a truncated file has none and fails to open instead of decoding
with missing rows.

Verified with rawpy 0.28 / LibRaw 0.22: `raw_image` equals the mosaic; ActiveArea becomes
`sizes.top_margin` / `left_margin` and crops `raw_image_visible`; ExposureTime and ISOSpeedRatings (EXIF IFD)
come back as `other.shutter_speed` / `other.iso_speed`, DateTime as `other.timestamp`. rawpy 0.28 does not
expose the camera make or model, so UniqueCameraModel is there for other readers only. A monochrome file
(PhotometricInterpretation LinearRaw, one sample per pixel, one black level) reads back bit for bit with
`num_colors` 1. LibRaw cannot be asked what a file declares: after a monochrome file, it reads a CFA file that lacks
its CFAPattern as one colour too (its state carries over), so `full_size_images` reads the declaration itself.
"""

from __future__ import annotations

import re
import struct
from fractions import Fraction
from pathlib import Path
from typing import Any, BinaryIO, Sequence

import numpy as np

from benchctl.errors import BadValueError
from benchctl.files import atomic_write_bytes

CFA_LAYOUTS: dict[str, tuple[int, int, int, int]] = {
    "RGGB": (0, 1, 1, 2),
    "BGGR": (2, 1, 1, 0),
    "GRBG": (1, 0, 2, 1),
    "GBRG": (1, 2, 0, 1),
}
"""Colour of the 2x2 CFA cell in row-major order (0 = red, 1 = green, 2 = blue), as in the CFAPattern tag."""

_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _SRATIONAL, _IFD = 1, 2, 3, 4, 5, 10, 13
_FORMATS = {_BYTE: "B", _ASCII: "B", _SHORT: "H", _LONG: "I", _RATIONAL: "I", _SRATIONAL: "i"}  # per number
_D65 = 21  # CalibrationIlluminant code for the colour matrix
CFA, LINEAR_RAW = 32803, 34892
"""PhotometricInterpretation of a colour-filter-array image and of a linear one (monochrome with one sample)."""
XYZ_TO_LINEAR_SRGB = (
    (3.2404542, -1.5371385, -0.4985314),
    (-0.9692660, 1.8760108, 0.0415560),
    (0.0556434, -0.2040259, 1.0572252),
)
"""Default ColorMatrix1: declares the camera's R, G, B to be linear sRGB, so LibRaw's camera -> sRGB step is
the identity (verified: postprocess to sRGB returns the raw values) and its daylight balance is (1, 1, 1)."""
_DATETIME = re.compile(r"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d")


def _rational(value: float, signed: bool = False) -> tuple[int, int]:
    """Nearest TIFF (S)RATIONAL with a denominator up to 10**6 that fits 32 bits."""
    fraction = Fraction(value).limit_denominator(10**6)
    limit = 2**31 if signed else 2**32
    if not (-limit if signed else 0) <= fraction.numerator < limit:
        raise BadValueError(f"DNG value {value} does not fit a 32-bit rational")
    return fraction.numerator, fraction.denominator


def _entry(tag: int, kind: int, values: Sequence[Any]) -> tuple[int, int, int, bytes]:
    """One IFD entry: (tag, type, count, value bytes); rationals are given as (numerator, denominator) pairs."""
    flat = [part for value in values for part in (value if kind in (_RATIONAL, _SRATIONAL) else (value,))]
    return tag, kind, len(values), struct.pack(f"<{len(flat)}{_FORMATS[kind]}", *flat)


def _ascii(tag: int, text: str) -> tuple[int, int, int, bytes]:
    data = text.encode("ascii", "replace") + b"\0"
    return tag, _ASCII, len(data), data


def _black_levels(black_level: int | Sequence[int], white_level: int) -> list[int]:
    values = np.ravel(black_level)
    if values.size not in (1, 4):
        raise BadValueError(f"black_level must be one number or 4 (one per CFA position), got {values.size}")
    levels = [int(v) for v in np.broadcast_to(values, (4,))]
    if not all(0 <= level < white_level for level in levels):
        raise BadValueError(f"black levels {levels} must lie in 0 .. white_level - 1 = {white_level - 1}")
    return levels


def dng_bytes(
    mosaic: np.ndarray,
    *,
    cfa: str | None = "RGGB",
    black_level: int | Sequence[int] = 0,
    white_level: int = 65535,
    camera_model: str = "benchctl simulated camera",
    active_area: tuple[int, int, int, int] | None = None,
    as_shot_neutral: Sequence[float] = (1.0, 1.0, 1.0),
    color_matrix: Sequence[Sequence[float]] | None = None,
    exposure_s: float | None = None,
    iso: int | None = None,
    datetime: str | None = None,
) -> bytes:
    """The DNG file for a raw Bayer mosaic (H, W) uint16, as the sensor read it (margins included).

    cfa: the 2x2 layout at the top-left of the active area (the visible image), which is how LibRaw reads it;
    None for a monochrome sensor (LinearRaw, one plane: no CFA, one black level, a 1x3 colour matrix).
    black_level: one level, or 4 levels per CFA position in row-major order (BlackLevelRepeatDim 2x2).
    active_area: (top, left, bottom, right) of the exposed pixels; the rest are masked margins, as on a real
    sensor; top and left must be even (LibRaw rounds odd ones up and then misplaces per-position black levels).
    color_matrix: XYZ -> camera (ColorMatrix1, D65), by default XYZ -> linear sRGB (camera RGB = linear sRGB,
    so LibRaw's sRGB output equals the raw values). exposure_s / iso: EXIF ExposureTime / ISOSpeedRatings.
    datetime: "YYYY:MM:DD HH:MM:SS" (TIFF DateTime).
    """
    if not isinstance(mosaic, np.ndarray) or mosaic.ndim != 2 or mosaic.dtype != np.uint16:
        raise BadValueError(f"DNG mosaic must be a 2-D uint16 array, got {getattr(mosaic, 'dtype', type(mosaic))} "
                            f"with shape {getattr(mosaic, 'shape', '?')}")
    height, width = mosaic.shape
    pattern = None if cfa is None else CFA_LAYOUTS.get(cfa.upper())
    if cfa is not None and pattern is None:
        raise BadValueError(f"unknown CFA layout {cfa!r}; choose one of {', '.join(CFA_LAYOUTS)}")
    if not 0 < white_level <= 65535:
        raise BadValueError(f"white_level must be 1 .. 65535, got {white_level}")
    blacks = _black_levels(black_level, white_level)
    matrix = XYZ_TO_LINEAR_SRGB if color_matrix is None else color_matrix
    if np.shape(matrix) != (3, 3):
        raise BadValueError(f"color_matrix must be 3x3, got shape {np.shape(matrix)}")
    if len(as_shot_neutral) != 3 or not all(v > 0 for v in as_shot_neutral):
        raise BadValueError(f"as_shot_neutral must be 3 positive numbers, got {list(as_shot_neutral)}")

    if pattern is None:
        if len(set(blacks)) != 1:
            raise BadValueError(f"a monochrome DNG has one black level, got {blacks}")
        colour = [
            _entry(262, _SHORT, [LINEAR_RAW]),  # PhotometricInterpretation
            _entry(50713, _SHORT, [1, 1]),  # BlackLevelRepeatDim
            _entry(50714, _LONG, blacks[:1]),  # BlackLevel
            _entry(50721, _SRATIONAL, [_rational(v, signed=True) for v in matrix[1]]),  # ColorMatrix1: luminance
            _entry(50728, _RATIONAL, [_rational(as_shot_neutral[1])]),  # AsShotNeutral
        ]
    else:
        colour = [
            _entry(262, _SHORT, [CFA]),  # PhotometricInterpretation
            _entry(33421, _SHORT, [2, 2]),  # CFARepeatPatternDim
            _entry(33422, _BYTE, pattern),  # CFAPattern
            _entry(50710, _BYTE, [0, 1, 2]),  # CFAPlaneColor: R G B
            _entry(50711, _SHORT, [1]),  # CFALayout: rectangular
            _entry(50713, _SHORT, [2, 2]),  # BlackLevelRepeatDim
            _entry(50714, _LONG, blacks),  # BlackLevel, per CFA position
            _entry(50721, _SRATIONAL, [_rational(v, signed=True) for row in matrix for v in row]),  # ColorMatrix1
            _entry(50728, _RATIONAL, [_rational(v) for v in as_shot_neutral]),  # AsShotNeutral
        ]
    entries = colour + [
        _entry(254, _LONG, [0]),  # NewSubFileType: the main image
        _entry(256, _LONG, [width]),
        _entry(257, _LONG, [height]),
        _entry(258, _SHORT, [16]),  # BitsPerSample
        _entry(259, _SHORT, [1]),  # Compression: none
        _entry(273, _LONG, [8]),  # StripOffsets: the strip follows the header
        _entry(274, _SHORT, [1]),  # Orientation: top-left
        _entry(277, _SHORT, [1]),  # SamplesPerPixel
        _entry(278, _LONG, [height]),  # RowsPerStrip: one strip
        _entry(279, _LONG, [height * width * 2]),  # StripByteCounts
        _entry(284, _SHORT, [1]),  # PlanarConfiguration: chunky
        _entry(50706, _BYTE, [1, 4, 0, 0]),  # DNGVersion
        _entry(50707, _BYTE, [1, 1, 0, 0]),  # DNGBackwardVersion
        _ascii(50708, camera_model),  # UniqueCameraModel
        _entry(50717, _LONG, [white_level]),  # WhiteLevel
        _entry(50778, _SHORT, [_D65]),  # CalibrationIlluminant1
    ]
    if datetime is not None:
        if not _DATETIME.fullmatch(datetime):
            raise BadValueError(f"DNG datetime must look like 2024:05:31 14:03:59, got {datetime!r}")
        entries.append(_ascii(306, datetime))  # DateTime
    if active_area is not None:
        top, left, bottom, right = active_area
        if not (0 <= top < bottom <= height and 0 <= left < right <= width):
            raise BadValueError(f"active_area {tuple(active_area)} does not fit a {height}x{width} mosaic")
        if top % 2 or left % 2:
            raise BadValueError(f"active_area {tuple(active_area)}: top and left must be even (a whole CFA cell)")
        entries.append(_entry(50829, _LONG, [top, left, bottom, right]))  # ActiveArea
    # LibRaw reads ISOSpeedRatings only from the EXIF IFD, so the exposure goes there (its standard place).
    exif = []
    if exposure_s is not None:
        if not exposure_s > 0:
            raise BadValueError(f"exposure_s must be positive, got {exposure_s}")
        exif.append(_entry(33434, _RATIONAL, [_rational(exposure_s)]))  # ExposureTime
    if iso is not None:
        if not 0 < iso <= 65535:
            raise BadValueError(f"iso must be 1 .. 65535, got {iso}")
        exif.append(_entry(34855, _SHORT, [iso]))  # ISOSpeedRatings

    # Layout: header, the one strip, the EXIF IFD (if any), then IFD 0; all offsets are known in that order.
    pixels = mosaic.astype("<u2", copy=False).tobytes()
    offset = 8 + len(pixels)
    exif_ifd = _ifd(exif, offset) if exif else b""
    if exif:
        entries.append(_entry(34665, _LONG, [offset]))  # ExifIFD pointer
        offset += len(exif_ifd)
    header = struct.pack("<2sHI", b"II", 42, offset)
    return b"".join([header, pixels, exif_ifd, _ifd(entries, offset)])


def _ifd(entries: list[tuple[int, int, int, bytes]], offset: int) -> bytes:
    """An IFD placed at `offset` (even), followed by the values that do not fit in their entries."""
    entries = sorted(entries)
    records, extra = [], b""
    data_offset = offset + 2 + 12 * len(entries) + 4
    for tag, kind, count, data in entries:
        if len(data) <= 4:
            records.append(struct.pack("<HHI", tag, kind, count) + data.ljust(4, b"\0"))
        else:
            records.append(struct.pack("<HHII", tag, kind, count, data_offset + len(extra)))
            extra += data + b"\0" * (len(data) % 2)
    return struct.pack("<H", len(entries)) + b"".join(records) + struct.pack("<I", 0) + extra


def write_dng(path: Path | str, mosaic: np.ndarray, **options: Any) -> Path:
    """Write `dng_bytes(mosaic, **options)` to `path` atomically (a reader never sees half a frame)."""
    return atomic_write_bytes(Path(path), dng_bytes(mosaic, **options))


def full_size_images(stream: BinaryIO) -> list[tuple[int, int]]:
    """(PhotometricInterpretation, SamplesPerPixel) of each full-size image (NewSubFileType 0) of a TIFF-based file
    (DNG, CR2, ...), in IFD 0's chain and their SubIFDs; [] for a file that is not a TIFF or names none."""
    stream.seek(0)
    header = stream.read(8)
    if header[:4] not in (b"II*\0", b"MM\0*"):
        return []
    order = "<" if header[:2] == b"II" else ">"
    pending: list[int] = [struct.unpack(order + "I", header[4:])[0]]
    seen: set[int] = set()
    found: list[tuple[int, int]] = []
    while pending and len(seen) < 64:  # a damaged file may chain IFDs in a loop
        offset = pending.pop(0)
        if offset == 0 or offset in seen:
            continue
        seen.add(offset)
        stream.seek(offset)
        count_bytes = stream.read(2)
        if len(count_bytes) < 2:
            continue
        table = stream.read(12 * struct.unpack(order + "H", count_bytes)[0] + 4)
        values = {}
        for at in range(0, len(table) - 15, 12):
            tag, kind, count = struct.unpack_from(order + "HHI", table, at)
            if tag in (254, 262, 277) and count == 1:
                values[tag] = struct.unpack_from(order + ("H" if kind == _SHORT else "I"), table, at + 8)[0]
            elif tag == 330 and kind in (_LONG, _IFD):  # SubIFDs: inline when one, else at an offset
                if count == 1:
                    pending.append(struct.unpack_from(order + "I", table, at + 8)[0])
                else:
                    stream.seek(struct.unpack_from(order + "I", table, at + 8)[0])
                    pending.extend(struct.unpack(f"{order}{count}I", stream.read(4 * count)))
        if len(table) >= 4:
            pending.append(struct.unpack_from(order + "I", table, len(table) - 4)[0])  # the next IFD of the chain
        if values.get(254, 0) == 0 and 262 in values:
            found.append((values[262], values.get(277, 1)))
    return found
