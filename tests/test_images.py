"""Image files: RGB order both ways, dtypes kept, gray and alpha, atomic writes, errors naming the path."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from benchctl.errors import BenchctlError
from benchctl.images import read_image, write_png


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
    with pytest.raises(BenchctlError, match=f"{junk}: not an image OpenCV can decode"):
        read_image(junk)
