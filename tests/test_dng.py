"""The DNG writer: what LibRaw (rawpy) reads back from our files, bit for bit and tag by tag."""

from __future__ import annotations

import io
import struct
from datetime import datetime

import numpy as np
import pytest
import rawpy

from benchctl.dng import CFA, CFA_LAYOUTS, LINEAR_RAW, dng_bytes, full_size_images, write_dng
from benchctl.errors import BadValueError

SHAPE = (64, 96)
# LibRaw's colour index per CFA position: 0 R, 1 G, 2 B, 3 the second green (color_desc "RGBG").
LIBRAW_PATTERNS = {
    "RGGB": [[0, 1], [3, 2]],
    "BGGR": [[2, 3], [1, 0]],
    "GRBG": [[1, 0], [2, 3]],
    "GBRG": [[3, 2], [0, 1]],
}


def random_mosaic(seed: int = 0, bits: int = 14) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2**bits, SHAPE, dtype=np.uint16)


def ifd0_entries(data: bytes) -> dict[int, tuple[int, int, int]]:
    """tag -> (type, count, position of the entry) for IFD 0 of a little-endian TIFF."""
    assert data[:4] == b"II*\0"
    (offset,) = struct.unpack_from("<I", data, 4)
    (count,) = struct.unpack_from("<H", data, offset)
    entries = {}
    for k in range(count):
        position = offset + 2 + 12 * k
        tag, kind, n = struct.unpack_from("<HHI", data, position)
        entries[tag] = (kind, n, position)
    return entries


def without_tag(data: bytes, tag: int) -> bytes:
    """The same file with IFD 0's `tag` renamed to a private tag number that no reader knows."""
    position = ifd0_entries(data)[tag][2]
    return data[:position] + struct.pack("<H", 65000) + data[position + 2:]


@pytest.mark.parametrize("cfa", list(CFA_LAYOUTS))
def test_round_trip_is_bit_exact_with_the_written_pattern(cfa: str) -> None:
    mosaic = random_mosaic(seed=len(cfa) + ord(cfa[0]))
    with rawpy.imread(io.BytesIO(dng_bytes(mosaic, cfa=cfa, black_level=512, white_level=16383))) as raw:
        assert raw.raw_image.dtype == np.uint16
        np.testing.assert_array_equal(raw.raw_image, mosaic)
        np.testing.assert_array_equal(raw.raw_pattern, LIBRAW_PATTERNS[cfa])
        np.testing.assert_array_equal(raw.raw_colors_visible[:4, :4], np.tile(LIBRAW_PATTERNS[cfa], (2, 2)))
        assert raw.color_desc == b"RGBG"
        assert (raw.sizes.height, raw.sizes.width, raw.sizes.top_margin, raw.sizes.left_margin) == (*SHAPE, 0, 0)


def test_full_16_bit_range_round_trips() -> None:
    mosaic = np.arange(SHAPE[0] * SHAPE[1], dtype=np.uint16).reshape(SHAPE)
    mosaic[0, :2] = (0, 65535)
    with rawpy.imread(io.BytesIO(dng_bytes(mosaic, white_level=65535))) as raw:
        np.testing.assert_array_equal(raw.raw_image, mosaic)


@pytest.mark.parametrize("cfa", list(CFA_LAYOUTS))
def test_black_levels_per_cfa_position_and_white_level_read_back(cfa: str) -> None:
    blacks = [2048, 2049, 2050, 2051]  # row-major CFA positions
    data = dng_bytes(random_mosaic(), cfa=cfa, black_level=blacks, white_level=15000)
    with rawpy.imread(io.BytesIO(data)) as raw:
        per_channel = raw.black_level_per_channel  # indexed by LibRaw colour index
        by_position = [per_channel[index] for index in raw.raw_pattern.flat]
        assert by_position == blacks
        assert raw.white_level == 15000


def test_single_black_level_applies_to_every_channel() -> None:
    with rawpy.imread(io.BytesIO(dng_bytes(random_mosaic(), black_level=1024, white_level=4095))) as raw:
        assert raw.black_level_per_channel == [1024] * 4
        assert raw.white_level == 4095


@pytest.mark.parametrize("cfa", ["RGGB", "GBRG"])
def test_active_area_becomes_the_visible_crop(cfa: str) -> None:
    mosaic = random_mosaic(seed=3)
    data = dng_bytes(mosaic, cfa=cfa, black_level=[100, 200, 300, 400], white_level=16383,
                     active_area=(2, 4, 61, 91))
    with rawpy.imread(io.BytesIO(data)) as raw:
        sizes = raw.sizes
        assert (sizes.raw_height, sizes.raw_width) == SHAPE
        assert (sizes.top_margin, sizes.left_margin, sizes.height, sizes.width) == (2, 4, 59, 87)
        np.testing.assert_array_equal(raw.raw_image, mosaic)
        np.testing.assert_array_equal(raw.raw_image_visible, mosaic[2:61, 4:91])
        # The CFA pattern and the black levels are relative to the active area's corner (DNG spec).
        np.testing.assert_array_equal(raw.raw_colors_visible[:2, :2], LIBRAW_PATTERNS[cfa])
        assert [raw.black_level_per_channel[i] for i in raw.raw_colors_visible[:2, :2].flat] == [100, 200, 300, 400]


def test_odd_active_area_origin_is_refused() -> None:
    # LibRaw would round the margins up to (4, 6) and then apply the black levels to the wrong positions.
    with pytest.raises(BadValueError, match="even"):
        dng_bytes(random_mosaic(), active_area=(3, 5, 61, 91))
    with pytest.raises(BadValueError, match="does not fit"):
        dng_bytes(random_mosaic(), active_area=(2, 4, 66, 91))


def test_monochrome_is_read_by_libraw_as_one_colour_with_its_levels_and_crop() -> None:
    """What decode_raw relies on for a monochrome sensor (LinearRaw, one sample per pixel): the values bit for bit,
    one colour (`num_colors`; the 1x1 raw_pattern and the colour_desc mean nothing here), the one black level on
    every channel, the white level and the active area's crop; LibRaw's own output is one channel."""
    mosaic = random_mosaic(seed=4, bits=12)
    data = dng_bytes(mosaic, cfa=None, black_level=64, white_level=4095, active_area=(2, 4, 61, 91))
    assert ifd0_entries(data)[262][:2] == (3, 1) and 33422 not in ifd0_entries(data)  # LinearRaw, no CFAPattern
    with rawpy.imread(io.BytesIO(data)) as raw:
        np.testing.assert_array_equal(raw.raw_image, mosaic)
        np.testing.assert_array_equal(raw.raw_image_visible, mosaic[2:61, 4:91])
        assert raw.num_colors == 1 and raw.raw_pattern.shape == (1, 1)
        assert raw.black_level_per_channel == [64] * 4 and raw.white_level == 4095
        rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, user_wb=[1.0, 1.0, 1.0, 1.0],
                              output_color=rawpy.ColorSpace.raw, adjust_maximum_thr=0.0)
    assert rgb.shape == (59, 87, 1)


def under_a_thumbnail(data: bytes, sub_ifds: int) -> bytes:
    """The file laid out as cameras write DNGs: IFD 0 a small RGB preview (NewSubFileType 1) whose SubIFDs tag
    points `sub_ifds` times at the original IFD 0 (inline when one, else through an array)."""
    (raw_ifd,) = struct.unpack_from("<I", data, 4)
    array = len(data)
    tail = struct.pack(f"<{sub_ifds}I", *[raw_ifd] * sub_ifds) if sub_ifds > 1 else b""
    thumbnail = array + len(tail)
    pointer = raw_ifd if sub_ifds == 1 else array
    entries = [(254, 4, 1, 1), (262, 3, 1, 2), (277, 3, 1, 3), (330, 4, sub_ifds, pointer)]
    records = [struct.pack("<HHII", tag, kind, count, value) for tag, kind, count, value in entries]  # SHORTs too:
    # a value left-aligned in the 4 bytes, little-endian, is the same bytes as a LONG
    ifd = struct.pack("<H", len(entries)) + b"".join(records) + struct.pack("<I", 0)
    return data[:4] + struct.pack("<I", thumbnail) + data[8:] + tail + ifd


def test_full_size_images_says_what_the_file_declares() -> None:
    mono, bayer = dng_bytes(random_mosaic(), cfa=None), dng_bytes(random_mosaic(), cfa="GBRG")
    assert full_size_images(io.BytesIO(mono)) == [(LINEAR_RAW, 1)]
    assert full_size_images(io.BytesIO(bayer)) == [(CFA, 1)]
    for sub_ifds in (1, 2):  # the preview is not a full-size image; the raw one is found once
        assert full_size_images(io.BytesIO(under_a_thumbnail(mono, sub_ifds))) == [(LINEAR_RAW, 1)]
    assert full_size_images(io.BytesIO(b"\x89PNG\r\n\x1a\n" + bytes(40))) == []
    assert full_size_images(io.BytesIO(mono[:len(mono) // 2])) == []  # the directory is written last


def test_exposure_iso_and_datetime_read_back() -> None:
    data = dng_bytes(random_mosaic(), white_level=16383, exposure_s=1 / 125, iso=800,
                     datetime="2024:05:31 14:03:59")
    with rawpy.imread(io.BytesIO(data)) as raw:
        other = raw.other
        assert other.shutter_speed == pytest.approx(1 / 125, rel=1e-6)
        assert other.iso_speed == 800
        assert other.timestamp == datetime(2024, 5, 31, 14, 3, 59)


def test_long_exposure_is_a_whole_rational() -> None:
    data = dng_bytes(random_mosaic(), exposure_s=30.0)
    with rawpy.imread(io.BytesIO(data)) as raw:
        assert raw.other.shutter_speed == 30.0


def test_default_colour_matrix_makes_camera_rgb_linear_srgb() -> None:
    values = {0: 0.2, 1: 0.4, 2: 0.6}
    mosaic = np.empty(SHAPE, dtype=np.uint16)
    for k, colour in enumerate(CFA_LAYOUTS["GRBG"]):
        mosaic[k // 2::2, k % 2::2] = 1000 + round(values[colour] * 10000)
    with rawpy.imread(io.BytesIO(dng_bytes(mosaic, cfa="GRBG", black_level=1000, white_level=11000))) as raw:
        assert raw.daylight_whitebalance[:3] == pytest.approx([1, 1, 1], abs=1e-5)
        rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True,
                              adjust_maximum_thr=0)  # LibRaw's default output: sRGB
    np.testing.assert_allclose(rgb[32, 48] / 65535, [0.2, 0.4, 0.6], atol=2e-4)


def test_cfa_pattern_tag_is_always_written() -> None:
    for cfa, pattern in CFA_LAYOUTS.items():
        data = dng_bytes(random_mosaic(), cfa=cfa)
        entries = ifd0_entries(data)
        kind, count, position = entries[33422]
        assert (kind, count) == (1, 4)
        assert tuple(data[position + 8:position + 12]) == pattern
        assert entries[33421][:2] == (3, 2)  # CFARepeatPatternDim: SHORT x 2


def test_without_cfa_pattern_libraw_loses_the_layout() -> None:
    # Why the writer always writes the tag: without it LibRaw 0.22 sets an arbitrary `filters` code (it varied
    # between runs: 4x4 patterns of 1s and 3s, or a code rawpy has no pattern for), never the 2x2 cell we wrote.
    data = without_tag(dng_bytes(random_mosaic(), cfa="BGGR"), 33422)
    with rawpy.imread(io.BytesIO(data)) as raw:
        try:
            pattern = raw.raw_pattern
        except NotImplementedError:
            pattern = None
    assert pattern is None or pattern.shape != (2, 2)


def test_write_dng_writes_the_same_bytes_atomically(tmp_path) -> None:
    mosaic = random_mosaic()
    path = write_dng(tmp_path / "frame.dng", mosaic, cfa="GBRG", black_level=64, white_level=4095, iso=100)
    assert path == tmp_path / "frame.dng"
    assert path.read_bytes() == dng_bytes(mosaic, cfa="GBRG", black_level=64, white_level=4095, iso=100)
    assert [p.name for p in tmp_path.iterdir()] == ["frame.dng"]


@pytest.mark.parametrize(
    ("mosaic", "options", "message"),
    [
        (np.zeros(SHAPE, dtype=np.float32), {}, "uint16"),
        (np.zeros((4, 4, 3), dtype=np.uint16), {}, "2-D"),
        (np.zeros(SHAPE, dtype=np.uint16), {"cfa": "RGBG"}, "unknown CFA layout"),
        (np.zeros(SHAPE, dtype=np.uint16), {"black_level": 4095, "white_level": 4095}, "black levels"),
        (np.zeros(SHAPE, dtype=np.uint16), {"black_level": [1, 2, 3]}, "one per CFA position"),
        (np.zeros(SHAPE, dtype=np.uint16), {"cfa": None, "black_level": [1, 2, 1, 1]}, "monochrome DNG has one"),
        (np.zeros(SHAPE, dtype=np.uint16), {"white_level": 70000}, "white_level"),
        (np.zeros(SHAPE, dtype=np.uint16), {"color_matrix": [[1, 0], [0, 1]]}, "3x3"),
        (np.zeros(SHAPE, dtype=np.uint16), {"as_shot_neutral": (1, 0, 1)}, "as_shot_neutral"),
        (np.zeros(SHAPE, dtype=np.uint16), {"exposure_s": 0.0}, "exposure_s"),
        (np.zeros(SHAPE, dtype=np.uint16), {"iso": 0}, "iso"),
        (np.zeros(SHAPE, dtype=np.uint16), {"datetime": "2024-05-31T14:03:59"}, "datetime"),
    ],
)
def test_bad_arguments_are_refused(mosaic: np.ndarray, options: dict, message: str) -> None:
    with pytest.raises(BadValueError, match=message):
        dng_bytes(mosaic, **options)
