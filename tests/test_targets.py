"""Targets: charts (shape, range, determinism, pure primaries), image files, preparation, black channels."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from benchctl.errors import BenchctlError
from benchctl.images import write_png
from benchctl.optics.colour import srgb_to_linear
from benchctl.targets import (
    BLACK_INTENSITY,
    PHOTO_PREFIX,
    active_channels,
    list_targets,
    load_target,
    photo_path,
    photo_specs,
    prepare_target,
)

SIZE = (96, 160)


@pytest.mark.parametrize("spec", [spec for spec in list_targets() if spec.startswith("chart:")])
def test_charts_have_shape_range_and_are_deterministic(spec: str) -> None:
    image = load_target(spec, SIZE)
    assert image.shape == (*SIZE, 3) and image.dtype == np.float32
    assert image.min() >= 0.0 and image.max() <= 1.0
    assert np.array_equal(image, load_target(spec, SIZE))
    assert load_target(spec, (64, 64)).shape == (64, 64, 3)


def test_structured_charts_have_contrast() -> None:
    for name in ("siemens", "wedge", "text", "grid", "bars"):
        image = load_target(f"chart:{name}", SIZE)
        assert image.min() == 0.0 and image.max() == 1.0, name
        assert 0.02 < image.mean() < 0.9, name


def test_bars_contain_pure_primaries_white_and_black() -> None:
    pixels = {tuple(p) for p in load_target("chart:bars", SIZE).reshape(-1, 3).tolist()}
    for colour in ((1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1), (0, 0, 0)):
        assert colour in pixels


def test_unknown_chart_lists_the_known_ones() -> None:
    with pytest.raises(BenchctlError, match="unknown chart 'chart:star'; known charts: chart:siemens, chart:wedge"):
        load_target("chart:star", SIZE)


def test_grayscale_png_loads_as_three_equal_channels(tmp_path: Path) -> None:
    gray = np.arange(64, dtype=np.uint8).reshape(8, 8) * 4
    write_png(tmp_path / "gray.png", gray)
    image = load_target(tmp_path / "gray.png", SIZE)
    assert image.shape == (8, 8, 3)  # files keep their own size
    assert np.array_equal(image[..., 0], image[..., 1]) and np.array_equal(image[..., 0], image[..., 2])
    np.testing.assert_allclose(image[..., 0], gray / 255.0, atol=1e-7)


def test_sixteen_bit_png_keeps_precision(tmp_path: Path) -> None:
    levels = np.arange(0, 65536, 257 // 4, dtype=np.uint16)[: 16 * 16].reshape(16, 16)
    write_png(tmp_path / "deep.png", np.stack([levels] * 3, axis=-1))
    image = load_target(str(tmp_path / "deep.png"), SIZE)
    np.testing.assert_allclose(image[..., 1], levels / 65535.0, atol=1e-7)
    assert len(np.unique(image)) == len(np.unique(levels))  # finer than 8-bit steps survive


def test_pure_red_png_is_red(tmp_path: Path) -> None:
    bgr = np.zeros((6, 6, 3), np.uint8)
    bgr[..., 2] = 255  # red in OpenCV's own order, written without benchctl
    ok, data = cv2.imencode(".png", bgr)
    (tmp_path / "red.png").write_bytes(data.tobytes())
    image = load_target(tmp_path / "red.png", SIZE)
    assert (image[..., 0] == 1.0).all() and (image[..., 1:] == 0.0).all()


def test_alpha_is_dropped(tmp_path: Path) -> None:
    bgra = np.full((4, 4, 4), 255, np.uint8)
    bgra[..., 3] = 0
    ok, data = cv2.imencode(".png", bgra)
    (tmp_path / "alpha.png").write_bytes(data.tobytes())
    assert load_target(tmp_path / "alpha.png", SIZE).shape == (4, 4, 3)


def test_missing_or_unreadable_file(tmp_path: Path) -> None:
    with pytest.raises(BenchctlError, match="missing.png: cannot read image"):
        load_target(str(tmp_path / "missing.png"), SIZE)
    (tmp_path / "bad.jpg").write_text("text")
    with pytest.raises(BenchctlError, match="bad.jpg: not a PNG, JPEG, BMP, TIFF or WebP image"):
        load_target(str(tmp_path / "bad.jpg"), SIZE)


def test_prepare_target_pads_with_zeros_and_keeps_amplitude_inside() -> None:
    srgb = np.zeros((24, 40, 3), np.float32)
    srgb[..., 0], srgb[..., 1], srgb[..., 2] = 1.0, 0.5, 0.0
    amplitude = prepare_target(srgb, (64, 96), (48, 80))  # enlarged 2x into the ROI
    assert amplitude.shape == (3, 64, 96) and amplitude.dtype == torch.float32
    inside = amplitude[:, 8:56, 8:88]
    expected = srgb_to_linear(torch.tensor([1.0, 0.5, 0.0])).sqrt()
    torch.testing.assert_close(inside, expected[:, None, None].expand_as(inside))
    outside = amplitude.clone()
    outside[:, 8:56, 8:88] = 0
    assert (outside == 0).all()


def test_prepare_target_averages_in_linear_light_when_shrinking() -> None:
    srgb = np.zeros((8, 8, 3), np.float32)
    srgb[:, ::2] = 1.0  # black/white columns: the average light is half of white
    amplitude = prepare_target(srgb, (6, 6), (4, 4))
    torch.testing.assert_close(amplitude[:, 1:5, 1:5], torch.full((3, 4, 4), 0.5**0.5))


def test_prepare_target_rejects_a_roi_larger_than_the_grid() -> None:
    with pytest.raises(ValueError, match="does not fit"):
        prepare_target(np.zeros((8, 8, 3), np.float32), (16, 16), (20, 16))


def test_active_channels() -> None:
    green = prepare_target(load_target("chart:green", (16, 16)), (32, 32), (16, 16))
    assert active_channels(green) == [False, True, False]
    faint = np.zeros((4, 4, 3), np.float32)
    faint[0, 0] = [1 / 255, 0.4 / 255, 0.0]  # one 8-bit step is light; below half a step is black
    assert active_channels(prepare_target(faint, (4, 4), (4, 4))) == [True, False, False]
    assert BLACK_INTENSITY == pytest.approx(0.5 / 255 / 12.92)


def test_photos_are_split_into_disjoint_held_out_and_training_sets() -> None:
    held_out, training = photo_specs("eval"), photo_specs("train")
    assert held_out == ["photo:astronaut", "photo:coffee", "photo:chelsea", "photo:rocket"]
    assert len(training) == 8 and not set(held_out) & set(training)
    assert set(held_out) | set(training) == {s for s in list_targets() if s.startswith(PHOTO_PREFIX)}
    with pytest.raises(ValueError, match="'eval' or 'train'"):
        photo_specs("test")


def test_photos_load_at_their_own_resolution_from_the_installed_package() -> None:
    coffee = load_target("photo:coffee", SIZE)
    assert coffee.shape == (400, 600, 3) and coffee.dtype == np.float32
    assert 0.0 <= coffee.min() < 0.05 and 0.95 < coffee.max() <= 1.0
    assert not np.array_equal(coffee[:, :, 0], coffee[:, :, 2])  # a colour photograph, not gray
    camera = load_target("photo:camera", SIZE)  # gray photos become three equal channels
    assert camera.shape == (512, 512, 3) and np.array_equal(camera[:, :, 0], camera[:, :, 1])
    assert photo_path("photo:coffee").name == "coffee.png"


def test_unknown_photo_and_missing_scikit_image_are_one_line_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(BenchctlError, match="unknown photo 'photo:lena'; known photos: photo:astronaut"):
        load_target("photo:lena", SIZE)
    monkeypatch.setattr("benchctl.targets.importlib.util.find_spec", lambda name: None)
    with pytest.raises(BenchctlError, match=r"photo:coffee: .*pip install 'benchctl\[photos\]'"):
        load_target("photo:coffee", SIZE)


def test_run_labels_strip_the_target_kind() -> None:
    from benchctl.runner.steps import target_label

    taken: set[str] = set()
    labels = [target_label(s, taken) for s in ("chart:bars", "photo:coffee", "pics/coffee.png", "photo:coffee")]
    assert labels == ["bars", "coffee", "coffee-2", "coffee-3"]
