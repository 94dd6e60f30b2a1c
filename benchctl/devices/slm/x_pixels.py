"""How gray levels become the pixels of an X11 TrueColor visual, exactly.

A visual says where each colour sits in a pixel (red, green and blue masks: depth 24 has 8 bits each, depth 30 has
10, depth 16 has 5, 6 and 5) and the pixmap format of its depth says how many bits a pixel takes in an image (32 for
depths 24 and 30, 16 for depth 16), padded per row to the server's scanline unit, in the server's byte order. A gray
level g of a `bit_depth`-bit SLM goes into every channel as g << (channel bits - bit_depth): the channel's top
`bit_depth` bits are g and the rest are zero, so a link or panel that takes only the top bits (truncating, rounding
or dithering them away) gets g exactly. A channel narrower than the SLM's bit depth cannot carry every gray level:
such a visual is refused, never shown approximately.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from benchctl.devices.errors import DeviceError

_TRUE_COLOR = 4  # X11 visual class TrueColor
_CHANNELS = ("red", "green", "blue")


def _field(mask: int) -> tuple[int, int]:
    """(lowest bit, number of bits) of a contiguous channel mask."""
    shift = (mask & -mask).bit_length() - 1
    bits = bin(mask).count("1")
    return shift, bits


@dataclass(frozen=True)
class PixelLayout:
    """Where R, G and B sit in a pixel of one visual, and how an image of that depth is laid out."""

    depth: int
    bits_per_pixel: int
    scanline_pad: int  # bits each row is padded to
    msb_first: bool  # the server's image byte order
    shifts: tuple[int, int, int]  # lowest bit of R, G, B
    bits: tuple[int, int, int]  # bits of R, G, B

    @classmethod
    def of_screen(cls, display: Any, screen: int) -> PixelLayout:
        """The layout of `screen`'s root visual (the one the SLM's window uses); DeviceError for a visual that is
        not TrueColor (a palette: gray levels would go through a colour map)."""
        root = display.screen(screen)
        visual = next((v for d in root.allowed_depths for v in d.visuals if v.visual_id == root.root_visual), None)
        if visual is None or visual.visual_class != _TRUE_COLOR:
            kind = "unknown" if visual is None else f"class {visual.visual_class}"
            raise DeviceError(f"screen {screen} of X display {display.get_display_name()} has a {kind} visual at depth "
                              f"{root.root_depth}, not TrueColor: gray levels would pass through a colour map")
        info = display.display.info
        fmt = next(f for f in info.pixmap_formats if f.depth == root.root_depth)
        fields = [_field(getattr(visual, f"{name}_mask")) for name in _CHANNELS]
        return cls(root.root_depth, fmt.bits_per_pixel, fmt.scanline_pad, info.image_byte_order == 1,
                   (fields[0][0], fields[1][0], fields[2][0]), (fields[0][1], fields[1][1], fields[2][1]))

    def describe(self) -> str:
        return f"depth {self.depth} ({'/'.join(str(b) for b in self.bits)} bits per R/G/B)"

    def check(self, bit_depth: int, where: str) -> None:
        """DeviceError unless every channel holds `bit_depth` bits (every gray level exactly)."""
        if min(self.bits) < bit_depth or self.bits_per_pixel not in (16, 32):
            raise DeviceError(f"{where} is at {self.describe()}: the SLM's {bit_depth}-bit gray levels need "
                              f"{bit_depth} bits in every channel; run that output's X screen at depth 24 or 30 (or "
                              f"set slm.bit_depth to what the panel takes)")

    def image(self, gray: np.ndarray, bit_depth: int) -> np.ndarray:
        """`gray` ((H, W), levels below 2^bit_depth) as the bytes of a ZPixmap image: (H, padded row bytes) uint8."""
        level = gray.astype(np.uint32)
        pixels = np.zeros(gray.shape, np.uint32)
        for shift, bits in zip(self.shifts, self.bits):
            pixels |= (level << (bits - bit_depth)) << shift
        unit = np.dtype(f"{'>' if self.msb_first else '<'}u{self.bits_per_pixel // 8}")
        row = gray.shape[1] * unit.itemsize
        padded = -(-row * 8 // self.scanline_pad) * self.scanline_pad // 8
        out = np.zeros((gray.shape[0], padded), np.uint8)
        out[:, :row] = pixels.astype(unit).view(np.uint8).reshape(gray.shape[0], row)
        return out
