"""An HDMI/DisplayPort SLM driven as a monitor through the Linux framebuffer device (/dev/fbN), no GUI toolkit.

The device's geometry comes from two ioctls (FBIOGET_VSCREENINFO, FBIOGET_FSCREENINFO) whose structs are
declared below exactly as in linux/fb.h, with native alignment: on 64-bit Linux `bits_per_pixel` sits at byte
24 of fb_var_screeninfo (160 bytes) and `line_length` at byte 48 of fb_fix_screeninfo (80 bytes; `unsigned
long smem_start` is 8 bytes there, and 2 bytes of padding follow `ywrapstep`). The visible area is mapped
with mmap and each row is written at the device's real stride (line_length), leaving its padding alone.

Pixel formats: 32 bpp (XRGB8888 and relatives: the gray level goes into the R, G and B bytes at the offsets the
device reports, alpha if any set opaque), 16 bpp (RGB565: gray reduced to each colour's bits) and 8 bpp
grayscale. The gray level enters each colour as its top bits. The geometry source is injectable, so tests
run against a regular file and a fake geometry.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import mmap
import os
import struct
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

import numpy as np

from benchctl.devices.errors import DeviceError
from benchctl.devices.slm.base import SLM
from benchctl.errors import BadValueError
from benchctl.profiles import SLMConfig

FBIOGET_VSCREENINFO = 0x4600
FBIOGET_FSCREENINFO = 0x4602
FBIO_WAITFORVSYNC = 0x40044620  # _IOW('F', 0x20, __u32)
_VSYNC_UNSUPPORTED = {errno.ENOTTY, errno.EINVAL, errno.EOPNOTSUPP}


class FbBitfield(ctypes.Structure):
    """struct fb_bitfield."""

    _fields_ = [("offset", ctypes.c_uint32), ("length", ctypes.c_uint32), ("msb_right", ctypes.c_uint32)]


class FbVarScreeninfo(ctypes.Structure):
    """struct fb_var_screeninfo (linux/fb.h): the video mode."""

    _fields_ = [
        *((name, ctypes.c_uint32) for name in (
            "xres", "yres", "xres_virtual", "yres_virtual", "xoffset", "yoffset", "bits_per_pixel", "grayscale")),
        *((name, FbBitfield) for name in ("red", "green", "blue", "transp")),
        *((name, ctypes.c_uint32) for name in (
            "nonstd", "activate", "height", "width", "accel_flags", "pixclock", "left_margin", "right_margin",
            "upper_margin", "lower_margin", "hsync_len", "vsync_len", "sync", "vmode", "rotate", "colorspace")),
        ("reserved", ctypes.c_uint32 * 4),
    ]


class FbFixScreeninfo(ctypes.Structure):
    """struct fb_fix_screeninfo (linux/fb.h): the memory layout."""

    _fields_ = [
        ("id", ctypes.c_char * 16),
        ("smem_start", ctypes.c_ulong),
        ("smem_len", ctypes.c_uint32),
        ("type", ctypes.c_uint32),
        ("type_aux", ctypes.c_uint32),
        ("visual", ctypes.c_uint32),
        ("xpanstep", ctypes.c_uint16),
        ("ypanstep", ctypes.c_uint16),
        ("ywrapstep", ctypes.c_uint16),
        ("line_length", ctypes.c_uint32),
        ("mmio_start", ctypes.c_ulong),
        ("mmio_len", ctypes.c_uint32),
        ("accel", ctypes.c_uint32),
        ("capabilities", ctypes.c_uint16),
        ("reserved", ctypes.c_uint16 * 2),
    ]


class Bitfield(NamedTuple):
    """Where one colour sits in a pixel word: bit offset and bit length."""

    offset: int
    length: int


@dataclass(frozen=True)
class FramebufferGeometry:
    """What the driver needs to know about a framebuffer: visible mode, pixel format and memory layout."""

    xres: int
    yres: int
    bits_per_pixel: int
    line_length: int  # bytes from one row to the next (>= xres * bytes per pixel)
    smem_len: int  # bytes of framebuffer memory to map
    red: Bitfield = Bitfield(16, 8)
    green: Bitfield = Bitfield(8, 8)
    blue: Bitfield = Bitfield(0, 8)
    transp: Bitfield = Bitfield(0, 0)
    xres_virtual: int = 0
    yres_virtual: int = 0
    xoffset: int = 0  # visible area within the virtual one
    yoffset: int = 0
    grayscale: int = 0  # 1: grayscale, > 1: a FOURCC format

    @classmethod
    def from_structs(cls, var: FbVarScreeninfo, fix: FbFixScreeninfo) -> FramebufferGeometry:
        """The geometry the two ioctls reported."""
        def bits(field: FbBitfield) -> Bitfield:
            return Bitfield(field.offset, field.length)

        return cls(
            xres=var.xres, yres=var.yres, bits_per_pixel=var.bits_per_pixel, line_length=fix.line_length,
            smem_len=fix.smem_len, red=bits(var.red), green=bits(var.green), blue=bits(var.blue),
            transp=bits(var.transp), xres_virtual=var.xres_virtual, yres_virtual=var.yres_virtual,
            xoffset=var.xoffset, yoffset=var.yoffset, grayscale=var.grayscale,
        )

    @property
    def bytes_per_pixel(self) -> int:
        return self.bits_per_pixel // 8


def read_geometry(fd: int) -> FramebufferGeometry:
    """Ask the framebuffer open on `fd` for its geometry (FBIOGET_VSCREENINFO / FBIOGET_FSCREENINFO)."""
    var, fix = FbVarScreeninfo(), FbFixScreeninfo()
    fcntl.ioctl(fd, FBIOGET_VSCREENINFO, var)
    fcntl.ioctl(fd, FBIOGET_FSCREENINFO, fix)
    return FramebufferGeometry.from_structs(var, fix)


class FramebufferSLM(SLM):
    """An SLM that is a monitor: gray frames written into /dev/fbN's memory (see module docstring)."""

    driver = "framebuffer"

    def __init__(
        self,
        config: SLMConfig,
        channels: Sequence[str] = (),
        *,
        geometry: Callable[[int], FramebufferGeometry] = read_geometry,
        vsync: bool = True,
    ) -> None:
        """`geometry(fd)` reads the device geometry (tests pass a fake); `vsync`: wait for vertical blank
        before writing a frame where the driver supports FBIO_WAITFORVSYNC."""
        super().__init__(config, channels)
        if not config.device:
            raise BadValueError('the framebuffer SLM needs slm.device in the profile, e.g. device = "/dev/fb1"')
        self.path = config.device
        self._read_geometry = geometry
        self._vsync = vsync
        self.geometry: FramebufferGeometry | None = None
        self._fd = -1
        self._map: mmap.mmap | None = None
        self._pixels: np.ndarray | None = None
        self._pack: Callable[[np.ndarray], np.ndarray] | None = None

    def _open(self) -> None:
        try:
            self._fd = os.open(self.path, os.O_RDWR | os.O_CLOEXEC)
        except FileNotFoundError:
            raise DeviceError(
                f"{self.path}: no such framebuffer device; is the SLM connected and enabled as a display? "
                f"`ls /dev/fb*` lists the framebuffers"
            ) from None
        except PermissionError:
            raise DeviceError(
                f"{self.path}: permission denied; framebuffers belong to the 'video' group: "
                f"`sudo usermod -aG video $USER` and log in again (check with `ls -l {self.path}`)"
            ) from None
        except OSError as exc:
            raise DeviceError(f"{self.path}: cannot open framebuffer: {exc.strerror or exc}") from None
        try:
            self._map_pixels()
        except BaseException:
            self._close()
            raise

    def _map_pixels(self) -> None:
        """Read and check the geometry, map the memory, and view the visible area as (H, W) pixel words."""
        try:
            geo = self._read_geometry(self._fd)
        except OSError as exc:
            raise DeviceError(
                f"{self.path}: not a framebuffer device (geometry ioctl failed: {exc.strerror or exc})"
            ) from None
        if (geo.yres, geo.xres) != self.shape:
            raise DeviceError(
                f"{self.path}: the display is {geo.xres} x {geo.yres} but the profile says slm.width x slm.height = "
                f"{self.config.width} x {self.config.height}; check the display mode (fbset, xrandr) and the "
                f"SLM's EDID, or fix the profile"
            )
        self._pack = _packer(geo, self.bit_depth, self.path)
        width_bytes = geo.xres * geo.bytes_per_pixel
        start = geo.yoffset * geo.line_length + geo.xoffset * geo.bytes_per_pixel
        end = start + (geo.yres - 1) * geo.line_length + width_bytes
        if geo.line_length < width_bytes or end > geo.smem_len:
            raise DeviceError(
                f"{self.path}: inconsistent geometry: {geo.yres} rows of {width_bytes} bytes at stride "
                f"{geo.line_length} from byte {start} do not fit in {geo.smem_len} bytes of framebuffer memory"
            )
        try:
            self._map = mmap.mmap(self._fd, geo.smem_len, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
        except (OSError, ValueError) as exc:
            raise DeviceError(f"{self.path}: cannot map framebuffer memory ({geo.smem_len} bytes): {exc}") from None
        dtype = np.dtype(f"u{geo.bytes_per_pixel}")
        self._pixels = np.ndarray(self.shape, dtype, buffer=self._map, offset=start,
                                  strides=(geo.line_length, geo.bytes_per_pixel))
        self.geometry = geo

    def _close(self) -> None:
        self._pixels = None  # the view must go before the map can close
        if self._map is not None:
            self._map.close()
            self._map = None
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        self.geometry = None

    def _display(self, gray: np.ndarray, channel: str | None) -> None:
        assert self._pixels is not None and self._pack is not None
        self._wait_vsync()
        self._pixels[...] = self._pack(gray)

    def _read_panel(self) -> np.ndarray | None:
        """The gray levels in the framebuffer's memory now: exactly the last frame where the memory holds its
        pixels, else each pixel's red bits (another program wrote the framebuffer)."""
        if self._pixels is None or self._pack is None or self.geometry is None:
            return None
        own = self.current()
        if own is not None and np.array_equal(self._pixels, self._pack(own)):
            return own
        geo = self.geometry
        field = Bitfield(0, 8) if geo.bits_per_pixel == 8 else geo.red
        level = (self._pixels.astype(np.uint32) >> np.uint32(field.offset)) & np.uint32((1 << field.length) - 1)
        return _top_bits(level, field.length, self.bit_depth).astype(self.gray_dtype)

    def _wait_vsync(self) -> None:
        """Wait for the vertical blank, so a frame starts being written as the panel starts a refresh."""
        if not self._vsync:
            return
        try:
            fcntl.ioctl(self._fd, FBIO_WAITFORVSYNC, struct.pack("I", 0))
        except OSError as exc:
            if exc.errno not in _VSYNC_UNSUPPORTED:
                raise DeviceError(f"{self.path}: waiting for vsync failed: {exc.strerror or exc}") from None
            self._vsync = False  # this driver has no vsync ioctl; do not ask again

    def info(self) -> dict[str, Any]:
        """The base description plus the framebuffer's geometry while open."""
        geo = self.geometry
        return {**super().info(), "framebuffer": asdict(geo) if geo else None}


def _packer(geo: FramebufferGeometry, bit_depth: int, path: str) -> Callable[[np.ndarray], np.ndarray]:
    """The function turning gray frames into pixel words of this framebuffer's format."""
    if geo.bits_per_pixel == 8 and geo.grayscale == 1:
        return lambda gray: _top_bits(gray, bit_depth, 8).astype(np.uint8)
    if geo.bits_per_pixel not in (16, 32) or geo.grayscale:
        raise DeviceError(
            f"{path}: unsupported pixel format ({geo.bits_per_pixel} bpp, grayscale={geo.grayscale}); supported: "
            f"32 bpp (XRGB8888), 16 bpp (RGB565), 8 bpp grayscale; e.g. `fbset -depth 32`"
        )
    for name, field in (("red", geo.red), ("green", geo.green), ("blue", geo.blue)):
        if not (0 < field.length and field.offset + field.length <= geo.bits_per_pixel):
            raise DeviceError(f"{path}: {name} bits {field} do not fit a {geo.bits_per_pixel}-bit pixel")
    dtype = np.dtype(f"u{geo.bytes_per_pixel}")
    alpha = ((1 << geo.transp.length) - 1) << geo.transp.offset  # opaque, where the format has alpha

    def pack(gray: np.ndarray) -> np.ndarray:
        wide = gray.astype(np.uint32)
        word = np.full(gray.shape, alpha, np.uint32)
        for field in (geo.red, geo.green, geo.blue):
            word |= _top_bits(wide, bit_depth, field.length) << np.uint32(field.offset)
        return word.astype(dtype)

    return pack


def _top_bits(gray: np.ndarray, bit_depth: int, length: int) -> np.ndarray:
    """`bit_depth`-bit gray levels as `length`-bit values: the top bits (or shifted up if length is larger)."""
    shift = bit_depth - length
    return gray >> shift if shift >= 0 else gray << -shift
