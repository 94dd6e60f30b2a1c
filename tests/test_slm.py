"""The SLM interface on the simulated panel: exact gray levels for known phases, offset, blazed carrier,
flips, persistence for other programs, refusals with clear messages, settle wait."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import numpy as np
import pytest
import torch

from benchctl.devices.errors import DeviceError
from benchctl.devices.sim.slm import SimSLM, read_displayed
from benchctl.devices.slm import open_slm
from benchctl.errors import BadValueError, BenchctlError
from benchctl.profiles import SLMConfig, load_profile

PI = math.pi
CHANNELS = ("red", "green", "blue")


def make_slm(height: int = 2, width: int = 4, **settings: object) -> SimSLM:
    """An open simulated SLM with no settle wait, linear tables, channels red/green/blue."""
    config = SLMConfig(width=width, height=height, pitch_um=8.0, bit_depth=8, settle_ms=0.0)
    return SimSLM(msgspec.structs.replace(config, **settings), CHANNELS).open()


def test_linear_table_gives_the_expected_gray_for_known_phases() -> None:
    slm = make_slm()
    phase = np.array([[0.0, PI, -PI / 2, PI / 2], [2 * PI, -PI, 3 * PI / 2, PI / 4]])
    shown = slm.show_phase(phase, "green")
    assert shown.dtype == np.uint8
    assert shown.tolist() == [[0, 128, 192, 64], [0, 128, 192, 32]]


def test_torch_and_numpy_phases_give_the_same_frame() -> None:
    slm = make_slm()
    phase = np.linspace(-3 * PI, 3 * PI, 8).reshape(2, 4)
    from_numpy = slm.show_phase(phase, "red")
    from_torch = slm.show_phase(torch.tensor(phase, dtype=torch.float32), "red")
    expected = np.round(np.mod(phase, 2 * PI) * 256 / (2 * PI)).astype(int) % 256  # no level is near a tie
    assert from_numpy.tolist() == from_torch.tolist() == expected.tolist()


def test_ten_bit_slm_shows_uint16_frames_and_persists_them_as_16_bit() -> None:
    slm = make_slm(bit_depth=10)
    shown = slm.show_phase(np.array([[0.0, PI, PI / 2, -PI / 2]] * 2), "blue")
    assert shown.dtype == np.uint16
    assert shown.tolist() == [[0, 512, 256, 768]] * 2
    frame, meta = read_displayed()
    assert frame is not None and frame.dtype == np.uint16
    assert frame.tolist() == shown.tolist()
    assert meta["bit_depth"] == 10


def test_phase_offset_shifts_the_gray_levels() -> None:
    slm = make_slm(phase_offset_rad=PI / 2)
    shown = slm.show_phase(np.array([[0.0, PI, 3 * PI / 2, -PI / 2]] * 2), "red")
    assert shown.tolist() == [[64, 192, 0, 0]] * 2


def test_blazed_grating_along_columns_is_a_sawtooth_with_the_period() -> None:
    slm = make_slm(height=2, width=16, grating_period_px=(0.0, 8.0))
    shown = slm.show_phase(np.zeros((2, 16)), "red")
    ramp = [0, 32, 64, 96, 128, 160, 192, 224]
    assert shown.tolist() == [ramp * 2] * 2


def test_blazed_grating_along_rows_and_both_axes() -> None:
    rows = make_slm(height=8, width=2, grating_period_px=(4.0, 0.0)).show_phase(np.zeros((8, 2)), "red")
    assert rows[:, 0].tolist() == rows[:, 1].tolist() == [0, 64, 128, 192] * 2
    both = make_slm(height=4, width=8, grating_period_px=(4.0, 8.0)).show_phase(np.zeros((4, 8)), "red")
    expected = [[(64 * r + 32 * c) % 256 for c in range(8)] for r in range(4)]
    assert both.tolist() == expected


def test_blazed_grating_with_a_fractional_period_rounds_to_the_nearest_level() -> None:
    # Period 2.5 px: phases 0, 0.8, 1.6, 2.4 (= 0.4), 3.2 (= 1.2) pi -> grays 0, 102.4, 204.8, 51.2, 153.6
    slm = make_slm(height=1, width=5, grating_period_px=(0.0, 2.5))
    assert slm.show_phase(np.zeros((1, 5)), "red").tolist() == [[0, 102, 205, 51, 154]]


def test_grating_adds_to_the_hologram_phase() -> None:
    slm = make_slm(height=1, width=4, grating_period_px=(0.0, 4.0))
    assert slm.show_phase(np.full((1, 4), PI), "red").tolist() == [[128, 192, 0, 64]]


def test_flips_mirror_the_displayed_frame() -> None:
    # Gray 16 * (4 r + c) on a 2 x 4 grid, shown through the linear table.
    phase = 2 * PI * 16 * np.arange(8).reshape(2, 4) / 256
    assert make_slm().show_phase(phase, "red").tolist() == [[0, 16, 32, 48], [64, 80, 96, 112]]
    assert make_slm(flip_x=True).show_phase(phase, "red").tolist() == [[48, 32, 16, 0], [112, 96, 80, 64]]
    assert make_slm(flip_y=True).show_phase(phase, "red").tolist() == [[64, 80, 96, 112], [0, 16, 32, 48]]
    both = make_slm(flip_x=True, flip_y=True).show_phase(phase, "red")
    assert both.tolist() == [[112, 96, 80, 64], [48, 32, 16, 0]]


def test_show_gray_is_shown_as_is_and_a_new_object_reads_it_back() -> None:
    gray = np.array([[0, 1, 254, 255], [7, 8, 9, 10]], dtype=np.uint8)
    slm = make_slm(flip_x=True, phase_offset_rad=1.0, grating_period_px=(0.0, 3.0))
    shown = slm.show_gray(gray)
    assert shown.tolist() == gray.tolist()
    gray[0, 0] = 99  # the caller's array is not the displayed frame
    assert slm.current().tolist()[0][0] == 0
    slm.close()

    frame, meta = SimSLM(slm.config, CHANNELS).read_displayed()
    assert frame is not None and frame.dtype == np.uint8
    assert frame.tolist() == [[0, 1, 254, 255], [7, 8, 9, 10]]
    assert {k: meta[k] for k in ("frame", "shape", "bit_depth", "channel")} == {
        "frame": 1, "shape": [2, 4], "bit_depth": 8, "channel": None,
    }


def test_frame_counter_and_channel_persist_across_objects(sim_state_dir: Path) -> None:
    make_slm().show_phase(np.zeros((2, 4)), "green")
    second = make_slm()
    second.show_phase(np.full((2, 4), PI), "blue")
    frame, meta = read_displayed()
    assert frame is not None and frame.tolist() == [[128] * 4] * 2
    assert (meta["frame"], meta["channel"]) == (2, "blue")
    # Only the current frame's file is kept.
    assert sorted(p.name for p in sim_state_dir.glob("slm*")) == ["slm-2.png", "slm.json"]


def test_nothing_displayed_yet() -> None:
    assert read_displayed() == (None, {})
    slm = make_slm()
    assert slm.current() is None


def test_blank_shows_zeros() -> None:
    slm = make_slm(bit_depth=12)
    slm.show_gray(np.full((2, 4), 4095, dtype=np.uint16))
    blank = slm.blank()
    assert blank.dtype == np.uint16 and blank.tolist() == [[0] * 4] * 2
    frame, _ = read_displayed()
    assert frame is not None and frame.tolist() == [[0] * 4] * 2


def test_current_is_the_last_frame_and_read_only() -> None:
    slm = make_slm()
    shown = slm.show_phase(np.full((2, 4), PI / 2), "red")
    assert slm.current() is shown
    with pytest.raises(ValueError):
        shown[0, 0] = 1


@pytest.mark.parametrize(
    ("gray", "message"),
    [
        (np.zeros((4, 2), np.uint8), "gray frame has shape (4, 2), expected (H, W) = (2, 4)"),
        (np.zeros((2, 4), np.uint16), "gray frame has dtype uint16, expected uint8 for a 8-bit SLM"),
        (np.zeros((2, 4), np.float64), "gray frame has dtype float64, expected uint8"),
    ],
)
def test_bad_gray_frames_are_refused(gray: np.ndarray, message: str) -> None:
    slm = make_slm()
    with pytest.raises(BadValueError, match="^SLM \\(sim\\): ") as info:
        slm.show_gray(gray)
    assert message in str(info.value)
    assert slm.current() is None


def test_gray_levels_beyond_the_bit_depth_are_refused() -> None:
    slm = make_slm(bit_depth=6)
    gray = np.full((2, 4), 63, np.uint8)
    assert slm.show_gray(gray).max() == 63
    gray[1, 2] = 64
    with pytest.raises(BadValueError, match=r"gray level 64 out of range 0\.\.63 \(6-bit SLM\)"):
        slm.show_gray(gray)


@pytest.mark.parametrize(
    ("phase", "message"),
    [
        (np.zeros((2, 5)), "phase has shape (2, 5), expected (H, W) = (2, 4)"),
        (np.zeros((1, 2, 4)), "phase has shape (1, 2, 4), expected (H, W) = (2, 4)"),
        (np.array([[0.0, np.nan, 1.0, np.inf]] * 2), "phase has 4 NaN or infinite values of 8"),
        (np.zeros((2, 4), np.uint8), "phase must be real radians (float), got uint8; use show_gray"),
        (np.zeros((2, 4), np.complex64), "phase must be real radians (float), got complex64"),
    ],
)
def test_bad_phases_are_refused(phase: np.ndarray, message: str) -> None:
    slm = make_slm()
    with pytest.raises(BadValueError) as info:
        slm.show_phase(phase, "red")
    assert message in str(info.value)
    assert read_displayed() == (None, {})


def test_unknown_channel_lists_the_known_ones() -> None:
    with pytest.raises(BenchctlError, match=r"no channel 'violet'; known channels: red, green, blue$"):
        make_slm().show_phase(np.zeros((2, 4)), "violet")


def test_settle_wait_follows_every_frame() -> None:
    slm = make_slm(settle_ms=25.0)
    waits: list[float] = []
    slm.sleep = waits.append
    slm.show_phase(np.zeros((2, 4)), "red")
    slm.show_gray(np.zeros((2, 4), np.uint8))
    slm.blank()
    assert waits == [0.025] * 3
    with pytest.raises(BadValueError):
        slm.show_phase(np.zeros((2, 5)), "red")
    assert waits == [0.025] * 3  # nothing shown, nothing to wait for


def test_showing_needs_an_open_slm() -> None:
    config = SLMConfig(width=4, height=2, pitch_um=8.0, bit_depth=8, settle_ms=0.0)
    slm = SimSLM(config, CHANNELS)
    with pytest.raises(DeviceError, match=r"SLM \(sim\) is not open"):
        slm.blank()
    with slm:
        assert slm.is_open
        slm.blank()
    assert not slm.is_open


def test_open_slm_builds_the_profiles_driver(small_profile_path: Path) -> None:
    profile = load_profile(small_profile_path)
    with open_slm(profile) as slm:
        assert isinstance(slm, SimSLM) and slm.is_open
        assert slm.shape == (64, 96)
        assert slm.pitch_m == pytest.approx(8e-6)
        assert (slm.bit_depth, slm.settle_s) == (8, 0.1)
        assert slm.channels == ("red", "green", "blue")
        info = slm.info()
    linear = "linear, 2 pi = gray 256"
    assert {k: v for k, v in info.items() if k not in ("device", "displayed")} == {
        "driver": "sim", "shape": [64, 96], "pitch_um": 8.0, "bit_depth": 8, "settle_ms": 100.0,
        "flip_x": False, "flip_y": False, "phase_offset_rad": 0.0, "grating_period_px": [0.0, 0.0],
        "luts": {"red": linear, "green": linear, "blue": linear},
    }
    assert not slm.is_open


def test_decode_inverts_encode_with_offset_carrier_and_flips() -> None:
    slm = make_slm(6, 10, flip_x=True, flip_y=True, phase_offset_rad=0.7, grating_period_px=(0.0, 4.0))
    phase = np.linspace(-3.0, 3.0, 60).reshape(6, 10)
    decoded = slm.decode(slm.encode(phase, "red"), "red").astype(np.float64)
    error = np.remainder(decoded - phase + math.pi, 2 * math.pi) - math.pi
    assert np.abs(error).max() <= math.pi / 256 + 1e-6  # within half a gray step of the 8-bit linear table
    changed = slm.encode(phase, "red")
    slm.close()  # one holder at a time
    assert not np.array_equal(changed, make_slm(6, 10).encode(phase, "red"))  # the settings really changed the frame
