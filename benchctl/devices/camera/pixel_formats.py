"""GenICam pixel formats (PFNC names) that benchctl keeps as RAW: what each says about the sensor, and the frame
a buffer of that format holds.

Unpacked formats only: 8-bit samples are one byte, 10 / 12 / 16-bit samples are one little-endian 16-bit word
each, low bits aligned (PFNC), so the values are the sensor's counts as delivered. The bit-packed variants
("p", "Packed") are refused: the camera can be set to the unpacked one.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from benchctl.devices.errors import DeviceError

_BAYER = {"RG": "RGGB", "GR": "GRBG", "GB": "GBRG", "BG": "BGGR"}  # PFNC order -> the 2x2 layout's name
_NAME = re.compile(r"(?:Bayer(RG|GR|GB|BG)(8|10|12|16)|Mono(8|10|12|16))")


@dataclass(frozen=True)
class PixelFormat:
    """One supported pixel format: its PFNC name, CFA layout (None: monochrome) and bits per sample."""

    name: str
    cfa: str | None
    bits: int

    @property
    def white_level(self) -> int:
        return (1 << self.bits) - 1

    @property
    def bytes_per_sample(self) -> int:
        return 1 if self.bits == 8 else 2

    def frame(self, data: bytes, width: int, height: int) -> np.ndarray:
        """The (height, width) uint16 frame of a buffer's image data, exactly the values delivered. DeviceError for
        a buffer of the wrong size, or a value above this format's white level (not low-bit aligned)."""
        expected = width * height * self.bytes_per_sample
        if len(data) != expected:
            raise DeviceError(f"{self.name} frame of {width} x {height} holds {len(data)} bytes, not {expected}: "
                              f"incomplete or not this format")
        dtype = np.uint8 if self.bits == 8 else np.dtype("<u2")
        samples = np.frombuffer(data, dtype).reshape(height, width)
        if self.bits not in (8, 16):
            top = int(samples.max(initial=0))
            if top > self.white_level:
                raise DeviceError(f"{self.name} frame holds the value {top}, above the {self.bits}-bit maximum "
                                  f"{self.white_level}: the camera does not deliver low-bit aligned samples")
        return samples.astype(np.uint16)


SUPPORTED = tuple(f"Bayer{order}{bits}" for bits in (8, 10, 12, 16) for order in _BAYER) + tuple(
    f"Mono{bits}" for bits in (8, 10, 12, 16))


def pixel_format(name: str) -> PixelFormat:
    """The PixelFormat called `name` (PFNC, as `get_pixel_format_as_string` gives it); DeviceError for others."""
    match = _NAME.fullmatch(name)
    if match is None:
        raise DeviceError(f"pixel format {name!r} is not one benchctl keeps as RAW (supported: "
                          f"{', '.join(SUPPORTED)}; packed variants are not): set camera.pixel_format")
    order, bayer_bits, mono_bits = match.groups()
    if order is not None:
        return PixelFormat(name, _BAYER[order], int(bayer_bits))
    return PixelFormat(name, None, int(mono_bits))
