"""RAW decoding to linear data: exact arithmetic, the CFA layout read from the file, and clear errors."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_dng import without_tag

from benchctl.capture.raw import MONO, RawImage, average_frames, decode_raw, linear_rgb, subtract_dark
from benchctl.capture.registration import cfa_positions
from benchctl.dng import CFA_LAYOUTS, dng_bytes, write_dng
from benchctl.errors import BadValueError, BenchctlError

SHAPE = (64, 96)
BLACK, WHITE = 2048, 15000
ABOVE_BLACK = {0: 1000, 1: 2000, 2: 3000}  # DN above black for R, G, B
LAYOUTS = list(CFA_LAYOUTS)


def uniform_field(cfa: str, above_black: dict[int, int] = ABOVE_BLACK, black: int = BLACK) -> np.ndarray:
    """A raw mosaic of one colour: each CFA position holds black + its colour's value."""
    mosaic = np.empty(SHAPE, dtype=np.uint16)
    for k, colour in enumerate(CFA_LAYOUTS[cfa]):
        mosaic[k // 2::2, k % 2::2] = black + above_black[colour]
    return mosaic


def expected(counts: float, black: float = BLACK, white: float = WHITE) -> np.float32:
    return np.float32((counts - black) / (white - black))


def linear_colour() -> np.ndarray:
    return np.array([expected(BLACK + ABOVE_BLACK[c]) for c in range(3)], dtype=np.float32)


@pytest.mark.parametrize("cfa", LAYOUTS)
def test_known_values_decode_exactly_with_the_layout_from_the_file(cfa: str) -> None:
    image = decode_raw(dng_bytes(uniform_field(cfa), cfa=cfa, black_level=BLACK, white_level=WHITE))
    assert image.layout == cfa
    np.testing.assert_array_equal(image.cfa, np.reshape(CFA_LAYOUTS[cfa], (2, 2)))
    assert image.mosaic.dtype == np.float32 and image.mosaic.shape == SHAPE
    for k, colour in enumerate(CFA_LAYOUTS[cfa]):
        assert np.all(image.mosaic[k // 2::2, k % 2::2] == expected(BLACK + ABOVE_BLACK[colour]))
    planes = image.planes()
    assert planes.shape == (3, 32, 48) and planes.dtype == np.float32
    for colour in range(3):
        assert np.all(planes[colour] == expected(BLACK + ABOVE_BLACK[colour])), "RGB"[colour]
    np.testing.assert_array_equal(image.black_levels, np.full((2, 2), BLACK))
    assert image.white_level == WHITE
    assert image.source == "<bytes>"
    assert not image.saturated.any() and image.saturation_fraction == 0.0


@pytest.mark.parametrize("cfa", LAYOUTS)
def test_black_level_per_cfa_position(cfa: str) -> None:
    blacks = [2000, 2010, 2020, 2030]
    mosaic = np.full(SHAPE, 3000, dtype=np.uint16)
    image = decode_raw(dng_bytes(mosaic, cfa=cfa, black_level=blacks, white_level=WHITE))
    np.testing.assert_array_equal(image.black_levels, np.reshape(blacks, (2, 2)))
    for k, black in enumerate(blacks):
        assert np.all(image.mosaic[k // 2::2, k % 2::2] == expected(3000, black=black))


def test_planes_average_the_two_greens_from_their_own_positions() -> None:
    mosaic = uniform_field("GBRG")
    mosaic[0::2, 0::2] = BLACK + 1800  # first green
    mosaic[1::2, 1::2] = BLACK + 2200  # second green
    planes = decode_raw(dng_bytes(mosaic, cfa="GBRG", black_level=BLACK, white_level=WHITE)).planes()
    assert np.all(planes[1] == np.float32((expected(BLACK + 1800) + expected(BLACK + 2200)) / 2))
    assert np.all(planes[0] == expected(BLACK + 1000)) and np.all(planes[2] == expected(BLACK + 3000))


def test_visible_area_only() -> None:
    mosaic = np.zeros(SHAPE, dtype=np.uint16)  # masked margins read 0, far below black
    mosaic[2:62, 4:92] = uniform_field("RGGB")[2:62, 4:92]
    image = decode_raw(dng_bytes(mosaic, cfa="RGGB", black_level=BLACK, white_level=WHITE,
                                 active_area=(2, 4, 62, 92)))
    assert image.mosaic.shape == (60, 88)
    assert image.layout == "RGGB"
    np.testing.assert_array_equal(image.planes()[:, 0, 0], linear_colour())
    assert image.mosaic.min() > 0


def test_saturated_pixels_are_flagged() -> None:
    mosaic = uniform_field("RGGB")
    mosaic[10, 10] = WHITE  # at the white level
    mosaic[11, 20] = 16383  # above it
    mosaic[12, 30] = WHITE - 1  # just below: not saturated
    image = decode_raw(dng_bytes(mosaic, cfa="RGGB", black_level=BLACK, white_level=WHITE))
    assert sorted(zip(*np.nonzero(image.saturated))) == [(10, 10), (11, 20)]
    assert image.saturation_fraction == 2 / mosaic.size
    assert image.mosaic[10, 10] == 1.0


@pytest.mark.parametrize("cfa", LAYOUTS)
def test_demosaic_of_a_uniform_colour_returns_that_colour_without_swapping_red_and_blue(cfa: str) -> None:
    rgb = decode_raw(dng_bytes(uniform_field(cfa), cfa=cfa, black_level=BLACK, white_level=WHITE)).demosaic()
    assert rgb.shape == (*SHAPE, 3) and rgb.dtype == np.float32
    np.testing.assert_allclose(rgb, np.broadcast_to(linear_colour(), rgb.shape), atol=1e-3)
    assert np.all(rgb[..., 0] < rgb[..., 1]) and np.all(rgb[..., 1] < rgb[..., 2])  # R < G < B here


def test_demosaic_keeps_negative_values() -> None:
    image = decode_raw(dng_bytes(uniform_field("BGGR"), cfa="BGGR", black_level=BLACK, white_level=WHITE))
    shifted = dataclasses.replace(image, mosaic=image.mosaic - np.float32(0.1))
    np.testing.assert_allclose(shifted.demosaic(), np.broadcast_to(linear_colour() - 0.1, (*SHAPE, 3)), atol=1e-4)


@pytest.mark.parametrize("cfa", ["RGGB", "GRBG"])
@pytest.mark.parametrize("above_black", [ABOVE_BLACK, {0: 11000, 1: 12000, 2: 12500}], ids=["dim", "bright"])
def test_linear_rgb_uses_the_linear_recipe(cfa: str, above_black: dict[int, int]) -> None:
    # "bright" peaks above 75 % of the white level, where LibRaw's default adjust_maximum_thr would rescale it.
    data = dng_bytes(uniform_field(cfa, above_black), cfa=cfa, black_level=BLACK, white_level=WHITE)
    colour = np.array([expected(BLACK + above_black[c]) for c in range(3)], dtype=np.float32)
    full = linear_rgb(data)
    half = linear_rgb(data, half_size=True)
    assert full.shape == (*SHAPE, 3) and half.shape == (32, 48, 3) and full.dtype == np.float32
    # LibRaw rounds down to 16 bits: at most 1 / 65535 below the exact value, never white balanced or rescaled.
    for rgb in (full, half):
        error = rgb - colour
        assert error.max() <= 0 and error.min() >= -1 / 65535


def test_linear_rgb_ignores_colour_matrix_and_white_balance() -> None:
    # With these tags LibRaw's daylight balance is (1.05, 1, 0.92) and the camera's as-shot one (2, 1, 1.25).
    data = dng_bytes(uniform_field("BGGR"), cfa="BGGR", black_level=BLACK, white_level=WHITE,
                     color_matrix=np.eye(3), as_shot_neutral=(0.5, 1.0, 0.8))
    error = linear_rgb(data) - linear_colour()
    assert error.max() <= 0 and error.min() >= -1 / 65535


def frame(above_black: int, cfa: str = "RGGB") -> RawImage:
    return decode_raw(dng_bytes(uniform_field(cfa, {0: above_black, 1: above_black, 2: above_black}), cfa=cfa,
                                black_level=BLACK, white_level=WHITE))


def test_average_frames() -> None:
    frames = [frame(1000), frame(2000), frame(4000)]
    saturated = frames[1].saturated.copy()
    saturated[5, 7] = True
    frames[1] = dataclasses.replace(frames[1], saturated=saturated)
    mean = average_frames(frames)
    np.testing.assert_allclose(mean.mosaic, (expected(BLACK + 1000) + expected(BLACK + 2000)
                                             + expected(BLACK + 4000)) / 3, rtol=1e-7)
    assert mean.mosaic.dtype == np.float32
    assert sorted(zip(*np.nonzero(mean.saturated))) == [(5, 7)]
    assert mean.layout == "RGGB" and mean.white_level == WHITE
    assert mean.source == "mean of 3 frames (<bytes> .. <bytes>)"


def test_the_average_of_one_frame_is_that_frame_without_a_copy() -> None:
    """CITL averages one frame per iteration by default: a float64 copy of an 18-megapixel mosaic cost it 0.1 to
    0.9 s per iteration (page faults), more than the decoding."""
    one = frame(1000)
    assert average_frames([one]) is one


def test_average_refuses_mismatched_frames() -> None:
    with pytest.raises(BadValueError, match="RGGB"):
        average_frames([frame(1000), frame(1000, cfa="BGGR")])
    with pytest.raises(BadValueError, match="at least one"):
        average_frames([])


def test_subtract_dark_keeps_signed_values() -> None:
    light, dark = frame(100), frame(150)
    dark_saturated = dark.saturated.copy()
    dark_saturated[0, 1] = True
    result = subtract_dark(light, dataclasses.replace(dark, saturated=dark_saturated))
    assert np.all(result.mosaic == expected(BLACK + 100) - expected(BLACK + 150))
    assert result.mosaic.max() < 0  # not clipped at 0
    assert sorted(zip(*np.nonzero(result.saturated))) == [(0, 1)]
    with pytest.raises(BadValueError, match="dark"):
        subtract_dark(light, dataclasses.replace(dark, mosaic=dark.mosaic[:, :-2]))


def test_a_monochrome_frame_is_one_plane_that_every_colour_reads() -> None:
    """A monochrome sensor's DNG (LinearRaw): exact linear values over the active area, MONO in every cell, so
    every colour's CFA positions are all four cells; planes() bins 2x2 for each colour, demosaic() and LibRaw's
    output carry the mosaic in R, G and B; the clip level is flagged."""
    counts = (BLACK + 7 * np.arange(SHAPE[0] * SHAPE[1]) % (WHITE - BLACK + 500)).astype(np.uint16).reshape(SHAPE)
    data = dng_bytes(counts, cfa=None, black_level=BLACK, white_level=WHITE, active_area=(2, 4, 62, 92))
    image = decode_raw(data)
    visible = counts[2:62, 4:92]
    assert image.layout == "mono" and image.monochrome and np.array_equal(image.cfa, np.full((2, 2), MONO))
    np.testing.assert_array_equal(image.mosaic, (visible.astype(np.float32) - BLACK) / np.float32(WHITE - BLACK))
    np.testing.assert_array_equal(image.saturated, visible >= WHITE)
    assert image.saturated.any() and image.white_level == WHITE and (image.black_levels == BLACK).all()
    for colour in range(3):
        assert cfa_positions(image.cfa, colour) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    binned = image.mosaic.reshape(30, 2, 44, 2).mean(axis=(1, 3))
    planes = image.planes()
    assert planes.shape == (3, 30, 44)
    for plane in planes:
        np.testing.assert_allclose(plane, binned, rtol=1e-6)
    np.testing.assert_array_equal(image.demosaic(), np.repeat(image.mosaic[:, :, None], 3, axis=2))
    clipped = np.clip(image.mosaic, 0, 1)[:, :, None]
    full, half = linear_rgb(data), linear_rgb(data, half_size=True)
    assert full.shape == (60, 88, 3) and half.shape == (30, 44, 3)
    assert (full - clipped).max() <= 1e-7 and (full - clipped).min() >= -1 / 65535  # rounded down to 16 bits
    np.testing.assert_allclose(half, np.repeat(full.reshape(30, 2, 44, 2, 3).mean(axis=(1, 3))[..., :1], 3, axis=2),
                               atol=1e-6)


def test_monochrome_and_bayer_frames_are_not_mixed() -> None:
    mono = decode_raw(dng_bytes(uniform_field("RGGB"), cfa=None, black_level=BLACK, white_level=WHITE))
    with pytest.raises(BadValueError, match=r"cannot average .*RGGB.* with .*mono"):
        average_frames([mono, frame(1000)])
    with pytest.raises(BadValueError, match=r"cannot subtract dark frame .*RGGB.* with .*mono"):
        subtract_dark(mono, frame(1000))
    assert average_frames([mono, mono]).layout == "mono"


def test_path_and_bytes_decode_the_same(tmp_path: Path) -> None:
    data = dng_bytes(uniform_field("GBRG"), cfa="GBRG", black_level=BLACK, white_level=WHITE)
    path = write_dng(tmp_path / "frame.dng", uniform_field("GBRG"), cfa="GBRG", black_level=BLACK, white_level=WHITE)
    from_file, from_bytes = decode_raw(path), decode_raw(data)
    assert from_file.source == str(path)
    np.testing.assert_array_equal(from_file.mosaic, from_bytes.mosaic)
    np.testing.assert_array_equal(from_file.cfa, from_bytes.cfa)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(BenchctlError, match=r"RAW file .*missing\.cr2 does not exist"):
        decode_raw(tmp_path / "missing.cr2")
    with pytest.raises(BenchctlError, match="is not a file"):
        decode_raw(tmp_path)


def test_png_given_as_raw(tmp_path: Path) -> None:
    path = tmp_path / "target.png"
    path.write_bytes(cv2.imencode(".png", np.zeros((32, 32, 3), dtype=np.uint8))[1].tobytes())
    with pytest.raises(BenchctlError, match=r"cannot decode RAW file .*target\.png: not a RAW file"):
        decode_raw(path)
    with pytest.raises(BenchctlError, match="cannot decode RAW file"):
        linear_rgb(path)


RGGB_FILE = dng_bytes(uniform_field("RGGB"), black_level=BLACK, white_level=WHITE)


@pytest.mark.parametrize("length", [0, 8, 100, len(RGGB_FILE) // 2, len(RGGB_FILE) - 200])
def test_truncated_dng_is_a_clear_error(length: int) -> None:
    with pytest.raises(BenchctlError, match=r"cannot decode RAW file <bytes>"):
        decode_raw(RGGB_FILE[:length])


def test_file_without_cfa_pattern_is_refused() -> None:
    """Refused on its own, and after a monochrome file, when LibRaw (its state carried over) reads it as one colour
    too: the file's own PhotometricInterpretation (CFA) says it is not monochrome."""
    data = without_tag(RGGB_FILE, 33422)
    with pytest.raises(BenchctlError, match=r"no CFA tag\?|without its CFAPattern tag\?"):
        decode_raw(data)
    assert decode_raw(dng_bytes(uniform_field("RGGB"), cfa=None, black_level=BLACK, white_level=WHITE)).monochrome
    with pytest.raises(BenchctlError, match=r"no CFA tag\?|without its CFAPattern tag\?"):
        decode_raw(data)
