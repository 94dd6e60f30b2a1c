"""Image files: RGB order both ways, dtypes kept, gray and alpha, atomic writes, errors naming the path."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import struct

from benchctl import images
from benchctl.errors import BenchctlError
from benchctl.images import header_size, read_image, write_png


def test_rgb_round_trip_keeps_channel_order_and_dtype(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    for dtype, top in ((np.uint8, 255), (np.uint16, 65535)):
        image = rng.integers(0, top + 1, size=(20, 30, 3)).astype(dtype)
        write_png(tmp_path / "rgb.png", image)
        back = read_image(tmp_path / "rgb.png")
        assert back.dtype == dtype and np.array_equal(back, image)


def test_written_red_is_red_for_other_programs(tmp_path: Path) -> None:
    red = np.zeros((4, 5, 3), np.uint8)
    red[..., 0] = 255
    write_png(tmp_path / "red.png", red)
    bgr = cv2.imdecode(np.fromfile(tmp_path / "red.png", np.uint8), cv2.IMREAD_UNCHANGED)
    assert (bgr[..., 2] == 255).all() and (bgr[..., :2] == 0).all()


def test_gray_and_alpha(tmp_path: Path) -> None:
    gray = np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000
    write_png(tmp_path / "gray.png", gray)
    assert np.array_equal(read_image(tmp_path / "gray.png"), gray)
    bgra = np.zeros((2, 2, 4), np.uint8)
    bgra[..., 0], bgra[..., 3] = 200, 100  # blue, half transparent
    ok, data = cv2.imencode(".png", bgra)
    (tmp_path / "alpha.png").write_bytes(data.tobytes())
    rgba = read_image(tmp_path / "alpha.png")
    assert rgba.shape == (2, 2, 4)
    assert (rgba[..., 2] == 200).all() and (rgba[..., 3] == 100).all() and (rgba[..., 0] == 0).all()


def test_write_replaces_atomically_and_leaves_no_temp_files(tmp_path: Path) -> None:
    target = tmp_path / "out.png"
    assert write_png(target, np.zeros((3, 3), np.uint8)) == target
    write_png(str(target), np.full((3, 3), 7, np.uint8))
    assert (read_image(target) == 7).all()
    assert [p.name for p in tmp_path.iterdir()] == ["out.png"]


def test_write_errors_name_the_path(tmp_path: Path) -> None:
    missing = tmp_path / "no_such_folder" / "x.png"
    with pytest.raises(BenchctlError, match=f"cannot write {missing}"):
        write_png(missing, np.zeros((2, 2), np.uint8))
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("")
    with pytest.raises(BenchctlError, match=f"cannot write {not_a_folder / 'x.png'}"):
        write_png(not_a_folder / "x.png", np.zeros((2, 2), np.uint8))
    with pytest.raises(ValueError, match="uint8 or uint16"):
        write_png(tmp_path / "f.png", np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match="shape"):
        write_png(tmp_path / "f.png", np.zeros((2, 2, 2), np.uint8))


def test_read_errors_name_the_path(tmp_path: Path) -> None:
    with pytest.raises(BenchctlError, match=f"{tmp_path / 'none.png'}: cannot read image"):
        read_image(tmp_path / "none.png")
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image")
    with pytest.raises(BenchctlError, match=f"{junk}: not a PNG, JPEG, BMP, TIFF or WebP image"):
        read_image(junk)


def tiff(height: int, width: int, order: str = "<", big: bool = False, pixels: bool = True) -> bytes:
    """An uncompressed 8-bit gray TIFF (BigTIFF when `big`) in byte order `order` ("<" or ">"), its pixels 0, 1,
    2, ... (only the header without `pixels`)."""
    count = height * width
    field = {3: order + ("H6x" if big else "H2x"), 4: order + ("I4x" if big else "I")}  # values left-justified
    header = 16 if big else 8
    tags = [(256, 4, width), (257, 4, height), (258, 3, 8), (259, 3, 1), (262, 3, 1), (273, 4, 0), (277, 3, 1),
            (278, 4, height), (279, 4, count)]
    data_at = header + (8 + 20 * len(tags) + 8 if big else 2 + 12 * len(tags) + 4)
    head = (b"II" if order == "<" else b"MM") + (struct.pack(order + "HHHQ", 43, 8, 0, header) if big
                                                 else struct.pack(order + "HI", 42, header))
    entries = b"".join(struct.pack(order + ("HHQ" if big else "HHI"), tag, kind, 1)
                       + struct.pack(field[kind], data_at if tag == 273 else value)
                       for tag, kind, value in tags)
    ifd = struct.pack(order + ("Q" if big else "H"), len(tags)) + entries + bytes(8 if big else 4)
    return head + ifd + ((np.arange(count) % 251).astype(np.uint8).tobytes() if pixels else b"")


def encoded(extension: str, image: np.ndarray, *params: int) -> bytes:
    ok, data = cv2.imencode(extension, image, list(params))
    assert ok
    return data.tobytes()


def test_every_accepted_format_is_measured_from_its_header(tmp_path: Path) -> None:
    rgb, rgba, gray = (np.zeros((37, 53, n), np.uint8) for n in (3, 4, 1))
    files = {
        "png": encoded(".png", rgb), "jpeg": encoded(".jpg", rgb), "bmp": encoded(".bmp", rgb),
        "bmp-gray": encoded(".bmp", gray), "tiff": encoded(".tif", rgb), "tiff-rgba": encoded(".tif", rgba),
        "webp-lossy": encoded(".webp", rgb, cv2.IMWRITE_WEBP_QUALITY, 80),
        "webp-lossless": encoded(".webp", rgb, cv2.IMWRITE_WEBP_QUALITY, 101),
        "webp-alpha": encoded(".webp", rgba, cv2.IMWRITE_WEBP_QUALITY, 80),
        "tiff-big-endian": tiff(37, 53, ">"), "bigtiff": tiff(37, 53, "<", big=True),
        "bigtiff-big-endian": tiff(37, 53, ">", big=True),
    }
    assert files["webp-alpha"][12:16] == b"VP8X" and files["webp-lossless"][12:16] == b"VP8L"
    for name, data in files.items():
        assert header_size(data) == (37, 53), name
        (tmp_path / name).write_bytes(data)
        assert read_image(tmp_path / name).shape[:2] == (37, 53), name
    ramp = read_image(tmp_path / "bigtiff-big-endian")
    assert np.array_equal(ramp.ravel(), np.arange(37 * 53) % 251)  # the hand-made TIFFs are real TIFFs
    exif = bytearray(files["jpeg"])  # an EXIF thumbnail's own frame header is not the image's
    thumbnail = encoded(".jpg", np.zeros((8, 8, 3), np.uint8))
    app1 = b"Exif\0\0" + thumbnail
    exif[2:2] = b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1
    assert header_size(bytes(exif)) == (37, 53)


@pytest.fixture
def no_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if OpenCV is asked to decode anything."""
    def refuse(*args: object) -> None:
        raise AssertionError("cv2.imdecode was called")

    monkeypatch.setattr(images.cv2, "imdecode", refuse)


@pytest.mark.parametrize("order, big", [("<", False), (">", False), ("<", True), (">", True)])
def test_a_tiff_above_the_pixel_limit_is_refused_before_decoding(tmp_path: Path, no_decoding: None, order: str,
                                                                 big: bool) -> None:
    """The red team's 6 MB TIFF asked OpenCV for 6.3 GB: its size is read from its header first."""
    path = tmp_path / "huge.tif"
    path.write_bytes(tiff(20000, 20000, order, big, pixels=False))  # the header is all it takes
    with pytest.raises(BenchctlError, match=r"huge.tif: 20000 x 20000 = 400,000,000 pixels is above the limit"):
        read_image(path)


@pytest.mark.parametrize("name, data, message", [
    ("gray.pgm", b"P5\n30000 30000\n255\n" + bytes(64), "not a PNG, JPEG, BMP, TIFF or WebP image"),
    ("light.hdr", b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 30000 +X 30000\n", "not a PNG, JPEG"),
    ("no-width.tif", tiff(20, 20)[:8] + struct.pack("<H", 1) + struct.pack("<HHII", 257, 4, 1, 20), "TIFF file "
     "whose header gives no image size"),
    ("cut.jpg", b"\xff\xd8\xff\xe0\x00\x10JFIF", "JPEG file whose header gives no image size"),
    ("zero.png", b"\x89PNG\r\n\x1a\n" + struct.pack(">I4sII", 13, b"IHDR", 0, 5), "PNG file whose header"),
])
def test_what_cannot_be_measured_is_not_decoded(tmp_path: Path, no_decoding: None, name: str, data: bytes,
                                                message: str) -> None:
    (tmp_path / name).write_bytes(data)
    with pytest.raises(BenchctlError, match=f"{name}: (a )?{message}"):
        read_image(tmp_path / name)
