"""The framebuffer SLM against a fake device (a regular file plus a fake geometry): the exact bytes at each
pixel for padded strides, pixel formats and flips; struct layouts as in linux/fb.h; refusals with advice."""

from __future__ import annotations

import ctypes
import dataclasses
import errno
import math
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from benchctl.devices.errors import DeviceError
from benchctl.devices.slm import framebuffer
from benchctl.devices.slm.framebuffer import (
    FBIO_WAITFORVSYNC,
    Bitfield,
    FbFixScreeninfo,
    FbVarScreeninfo,
    FramebufferGeometry,
    FramebufferSLM,
)
from benchctl.profiles import SLMConfig

pytestmark = pytest.mark.skipif(sys.byteorder != "little", reason="expected bytes are little-endian")
FILL = 0xAB  # what the fake framebuffer memory holds before: padding must keep it
XRGB = FramebufferGeometry(xres=5, yres=3, bits_per_pixel=32, line_length=5 * 4 + 12, smem_len=32 * 3 + 16)


def fake_slm(tmp_path: Path, geo: FramebufferGeometry, **settings: object) -> FramebufferSLM:
    """An open framebuffer SLM on a regular file of smem_len bytes, with `geo` as the device geometry."""
    device = tmp_path / "fb1"
    device.write_bytes(bytes([FILL]) * geo.smem_len)
    config = SLMConfig(width=geo.xres, height=geo.yres, pitch_um=8.0, driver="framebuffer", device=str(device),
                       settle_ms=0.0, **{"bit_depth": 8, **settings})
    return FramebufferSLM(config, ["red"], geometry=lambda fd: geo).open()


def expected_memory(geo: FramebufferGeometry, gray: np.ndarray, pixel: dict[int, bytes] | None = None,
                    top: int = 0, left: int = 0) -> bytes:
    """Framebuffer memory after writing `gray` at (top, left), by hand: FILL everywhere else."""
    memory = bytearray([FILL]) * geo.smem_len
    size = geo.bits_per_pixel // 8
    for r, c in np.ndindex(gray.shape):
        at = (top + r) * geo.line_length + (left + c) * size
        g = int(gray[r, c])
        memory[at:at + size] = pixel[g] if pixel else bytes([g, g, g, 0])
    return bytes(memory)


def shown_bytes(slm: FramebufferSLM) -> bytes:
    return Path(slm.path).read_bytes()


def test_xrgb8888_writes_gray_into_b_g_r_at_the_real_stride(tmp_path: Path) -> None:
    slm = fake_slm(tmp_path, XRGB)
    gray = (np.arange(15).reshape(3, 5) * 17).astype(np.uint8)
    slm.show_gray(gray)
    memory = shown_bytes(slm)
    assert memory[1 * 32 + 2 * 4: 1 * 32 + 3 * 4] == bytes([119, 119, 119, 0])  # pixel (1, 2), gray 7 * 17
    assert memory[20:32] == bytes([FILL]) * 12  # row 0's padding untouched
    assert memory == expected_memory(XRGB, gray)
    slm.close()
    assert shown_bytes(slm) == expected_memory(XRGB, gray)  # the panel keeps the frame


@pytest.mark.parametrize(
    ("fields", "pixel_of"),
    [
        # XBGR8888 with alpha: R in byte 0, B in byte 2, opaque alpha in byte 3
        ({"red": Bitfield(0, 8), "green": Bitfield(8, 8), "blue": Bitfield(16, 8), "transp": Bitfield(24, 8)},
         lambda g: bytes([g, g, g, 255])),
        # BGRX8888: the unused byte first
        ({"red": Bitfield(8, 8), "green": Bitfield(16, 8), "blue": Bitfield(24, 8)}, lambda g: bytes([0, g, g, g])),
    ],
)
def test_colour_offsets_come_from_the_device(tmp_path: Path, fields: dict, pixel_of: object) -> None:
    geo = dataclasses.replace(XRGB, **fields)
    slm = fake_slm(tmp_path, geo)
    gray = np.array([[0, 1, 128, 254, 255]] * 3, dtype=np.uint8)
    slm.show_gray(gray)
    assert shown_bytes(slm) == expected_memory(geo, gray, {g: pixel_of(g) for g in (0, 1, 128, 254, 255)})


def test_rgb565_quantises_gray_per_colour(tmp_path: Path) -> None:
    geo = FramebufferGeometry(xres=4, yres=2, bits_per_pixel=16, line_length=4 * 2 + 6, smem_len=14 * 2,
                              red=Bitfield(11, 5), green=Bitfield(5, 6), blue=Bitfield(0, 5))
    slm = fake_slm(tmp_path, geo)
    gray = np.array([[0, 7, 200, 255], [8, 4, 3, 252]], dtype=np.uint8)
    slm.show_gray(gray)
    # 7: G 1 -> 0x0020; 200: R 25, G 50, B 25 -> 0xCE59; 8: R 1, G 2, B 1 -> 0x0841; 4: G 1; 252: R 31, G 63, B 31
    pixel = {0: b"\x00\x00", 7: b"\x20\x00", 200: b"\x59\xce", 255: b"\xff\xff",
             8: b"\x41\x08", 4: b"\x20\x00", 3: b"\x00\x00", 252: b"\xff\xff"}
    assert shown_bytes(slm) == expected_memory(geo, gray, pixel)


def test_eight_bpp_grayscale(tmp_path: Path) -> None:
    geo = FramebufferGeometry(xres=3, yres=2, bits_per_pixel=8, line_length=8, smem_len=16, grayscale=1)
    slm = fake_slm(tmp_path, geo)
    gray = np.array([[0, 9, 255], [1, 2, 3]], dtype=np.uint8)
    slm.show_gray(gray)
    assert shown_bytes(slm) == expected_memory(geo, gray, {g: bytes([g]) for g in range(256)})


def test_ten_bit_gray_keeps_the_top_eight_bits_on_xrgb8888(tmp_path: Path) -> None:
    slm = fake_slm(tmp_path, XRGB, bit_depth=10)
    gray = np.array([[0, 3, 4, 512, 1023]] * 3, dtype=np.uint16)
    slm.show_gray(gray)
    assert shown_bytes(slm) == expected_memory(XRGB, gray >> 2)


def test_visible_area_starts_at_the_panned_offset(tmp_path: Path) -> None:
    geo = FramebufferGeometry(xres=2, yres=2, bits_per_pixel=32, line_length=16, smem_len=16 * 5,
                              xres_virtual=4, yres_virtual=5, xoffset=1, yoffset=3)
    slm = fake_slm(tmp_path, geo)
    gray = np.array([[10, 20], [30, 40]], dtype=np.uint8)
    slm.show_gray(gray)
    assert shown_bytes(slm) == expected_memory(geo, gray, top=3, left=1)
    assert shown_bytes(slm)[3 * 16 + 4: 3 * 16 + 8] == bytes([10, 10, 10, 0])


def test_show_phase_flips_reach_the_panel(tmp_path: Path) -> None:
    slm = fake_slm(tmp_path, XRGB, flip_x=True, flip_y=True)
    gray = (np.arange(15).reshape(3, 5) * 16).astype(np.uint8)
    shown = slm.show_phase(gray * (2 * math.pi / 256), "red")
    assert shown.tolist() == gray[::-1, ::-1].tolist()
    assert shown_bytes(slm) == expected_memory(XRGB, gray[::-1, ::-1])
    assert shown_bytes(slm)[:4] == bytes([224, 224, 224, 0])  # top-left shows the last pixel


def test_size_mismatch_is_refused_with_both_sizes(tmp_path: Path) -> None:
    device = tmp_path / "fb0"
    device.write_bytes(b"")
    geo = FramebufferGeometry(xres=1920, yres=1080, bits_per_pixel=32, line_length=7680, smem_len=7680 * 1080)
    config = SLMConfig(width=1920, height=1088, pitch_um=3.74, bit_depth=8, driver="framebuffer", device=str(device))
    slm = FramebufferSLM(config, geometry=lambda fd: geo)
    with pytest.raises(DeviceError) as info:
        slm.open()
    assert str(info.value) == (
        f"{device}: the display is 1920 x 1080 but the profile says slm.width x slm.height = 1920 x 1088; "
        "check the display mode (fbset, xrandr) and the SLM's EDID, or fix the profile"
    )
    assert not slm.is_open


def test_missing_device_names_the_path_and_how_to_look(tmp_path: Path) -> None:
    config = SLMConfig(width=4, height=2, pitch_um=8.0, bit_depth=8, driver="framebuffer",
                       device=str(tmp_path / "fb7"))
    with pytest.raises(DeviceError, match=r"fb7: no such framebuffer device.*`ls /dev/fb\*`"):
        FramebufferSLM(config).open()


def test_permission_denied_suggests_the_video_group(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(path: str, flags: int) -> int:
        raise PermissionError(errno.EACCES, "Permission denied", path)

    monkeypatch.setattr(framebuffer.os, "open", refuse)  # tests may run as root, where chmod 000 is no bar
    config = SLMConfig(width=4, height=2, pitch_um=8.0, bit_depth=8, driver="framebuffer", device="/dev/fb1")
    with pytest.raises(DeviceError, match=r"^/dev/fb1: permission denied; .*'video' group.*usermod -aG video"):
        FramebufferSLM(config).open()


def test_a_regular_file_is_not_a_framebuffer(tmp_path: Path) -> None:
    device = tmp_path / "notfb"
    device.write_bytes(bytes(64))
    config = SLMConfig(width=4, height=2, pitch_um=8.0, bit_depth=8, driver="framebuffer", device=str(device))
    with pytest.raises(DeviceError, match=r"notfb: not a framebuffer device \(geometry ioctl failed: "):
        FramebufferSLM(config).open()  # the real ioctls, which regular files refuse


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"bits_per_pixel": 24}, "unsupported pixel format (24 bpp, grayscale=0)"),
        ({"bits_per_pixel": 8}, "unsupported pixel format (8 bpp, grayscale=0)"),
        ({"grayscale": 0x34325258}, "unsupported pixel format (32 bpp, grayscale=875713112)"),
        ({"blue": Bitfield(28, 8)}, "blue bits Bitfield(offset=28, length=8) do not fit a 32-bit pixel"),
        ({"line_length": 16}, "3 rows of 20 bytes at stride 16"),
        ({"smem_len": 32 * 2 + 19}, "3 rows of 20 bytes at stride 32 from byte 0 do not fit in 83 bytes"),
    ],
)
def test_unusable_geometry_is_refused(tmp_path: Path, changes: dict, message: str) -> None:
    geo = dataclasses.replace(XRGB, **changes)
    with pytest.raises(DeviceError) as info:
        fake_slm(tmp_path, geo)
    assert message in str(info.value)


def test_memory_smaller_than_reported_is_refused(tmp_path: Path) -> None:
    slm = fake_slm(tmp_path, XRGB)
    slm.close()
    Path(slm.path).write_bytes(bytes(40))
    with pytest.raises(DeviceError, match=r"cannot map framebuffer memory \(112 bytes\)"):
        slm.open()


def test_vsync_is_waited_for_and_dropped_where_unsupported(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    slm = fake_slm(tmp_path, XRGB)
    requests: list[tuple[int, bytes]] = []

    def ioctl(fd: int, request: int, arg: bytes) -> None:
        requests.append((request, arg))
        raise OSError(errno.ENOTTY, "Inappropriate ioctl for device")

    monkeypatch.setattr(framebuffer.fcntl, "ioctl", ioctl)
    slm.blank()
    slm.blank()
    assert requests == [(0x40044620, b"\x00\x00\x00\x00")] and FBIO_WAITFORVSYNC == 0x40044620
    assert shown_bytes(slm) == expected_memory(XRGB, np.zeros((3, 5), np.uint8))


def test_vsync_failure_other_than_unsupported_is_an_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    slm = fake_slm(tmp_path, XRGB)

    def ioctl(fd: int, request: int, arg: bytes) -> None:
        raise OSError(errno.EIO, "Input/output error")

    monkeypatch.setattr(framebuffer.fcntl, "ioctl", ioctl)
    with pytest.raises(DeviceError, match=r"fb1: waiting for vsync failed: Input/output error"):
        slm.blank()


@pytest.mark.skipif(ctypes.sizeof(ctypes.c_ulong) != 8, reason="offsets of 64-bit Linux")
def test_struct_layouts_match_linux_fb_h_on_64_bit() -> None:
    assert ctypes.sizeof(FbVarScreeninfo) == 160 and ctypes.sizeof(FbFixScreeninfo) == 80
    offsets = {name: getattr(FbVarScreeninfo, name).offset
               for name in ("xres", "yres", "xres_virtual", "yoffset", "bits_per_pixel", "red", "green", "blue",
                            "transp", "reserved")}
    assert offsets == {"xres": 0, "yres": 4, "xres_virtual": 8, "yoffset": 20, "bits_per_pixel": 24, "red": 32,
                       "green": 44, "blue": 56, "transp": 68, "reserved": 144}
    assert (FbFixScreeninfo.smem_len.offset, FbFixScreeninfo.line_length.offset) == (24, 48)


@pytest.mark.skipif(ctypes.sizeof(ctypes.c_ulong) != 8, reason="offsets of 64-bit Linux")
def test_geometry_is_read_from_the_ioctl_structs() -> None:
    var, fix = bytearray(160), bytearray(80)
    struct.pack_into("<6I", var, 0, 1920, 1080, 1920, 2160, 0, 1080)  # xres .. yoffset (panned to 2nd buffer)
    struct.pack_into("<I", var, 24, 32)
    struct.pack_into("<12I", var, 32, 16, 8, 0, 8, 8, 0, 0, 8, 0, 24, 8, 0)  # red, green, blue, transp
    struct.pack_into("<I", fix, 24, 7680 * 2160)  # smem_len
    struct.pack_into("<I", fix, 48, 7936)  # line_length, padded
    geo = FramebufferGeometry.from_structs(FbVarScreeninfo.from_buffer_copy(var),
                                           FbFixScreeninfo.from_buffer_copy(fix))
    assert geo == FramebufferGeometry(
        xres=1920, yres=1080, bits_per_pixel=32, line_length=7936, smem_len=7680 * 2160,
        red=Bitfield(16, 8), green=Bitfield(8, 8), blue=Bitfield(0, 8), transp=Bitfield(24, 8),
        xres_virtual=1920, yres_virtual=2160, xoffset=0, yoffset=1080, grayscale=0,
    )


def test_info_reports_the_geometry_while_open(tmp_path: Path) -> None:
    slm = fake_slm(tmp_path, XRGB)
    info = slm.info()
    assert (info["driver"], info["device"]) == ("framebuffer", slm.path)
    assert info["framebuffer"]["line_length"] == 32 and info["framebuffer"]["red"] == (16, 8)
    slm.close()
    assert slm.info()["framebuffer"] is None


def test_showing_reads_the_framebuffer_back_and_knows_its_own_frames(tmp_path: Path) -> None:
    """What the panel shows, read from the framebuffer's memory: this connection's own frame exactly, with who
    showed it; a frame another program wrote, as its red bits, by nobody known."""
    import os

    slm = fake_slm(tmp_path, XRGB)
    before = slm.showing()
    assert before.by is None and before.frame is not None and (before.frame == FILL).all()
    gray = (np.arange(15).reshape(3, 5) * 17).astype(np.uint8)
    slm.show_gray(gray)
    own = slm.showing()
    assert np.array_equal(own.frame, gray) and own.frame_id == 1 and own.by.endswith(f"(pid {os.getpid()})")
    assert own.at == slm.presented_at and own.channel is None
    memory = bytearray(shown_bytes(slm))
    memory[4:8] = bytes([1, 2, 200, 0])  # another program writes pixel (0, 1): red 200
    Path(slm.path).write_bytes(bytes(memory))
    other = slm.showing()
    assert other.by is None and other.frame_id is None and other.frame[0, 1] == 200
    assert np.array_equal(np.delete(other.frame.ravel(), 1), np.delete(gray.ravel(), 1))
    slm.close()


def test_showing_a_ten_bit_frame_on_rgb565_is_exact_for_its_own_frames(tmp_path: Path) -> None:
    geo = FramebufferGeometry(xres=4, yres=2, bits_per_pixel=16, line_length=8, smem_len=16, red=Bitfield(11, 5),
                              green=Bitfield(5, 6), blue=Bitfield(0, 5))
    slm = fake_slm(tmp_path, geo, bit_depth=10)
    gray = np.array([[0, 1, 511, 1023], [7, 64, 700, 1000]], np.uint16)
    slm.show_gray(gray)
    assert np.array_equal(slm.showing().frame, gray)  # its own frame, though five bits of red cannot hold it
    slm.close()
