"""Phase <-> gray encoding: exact round trips, half-step accuracy, tables off 2 pi, wrapping, bad tables refused."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from benchctl.optics.phase_encoding import PhaseLUT, gray_to_phase, phase_to_gray

TWO_PI = 2 * math.pi


def circular_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = np.remainder(np.asarray(a, np.float64) - np.asarray(b, np.float64), TWO_PI)
    return np.minimum(d, TWO_PI - d)


@pytest.mark.parametrize("bit_depth", [8, 10])
def test_gray_phase_gray_is_exact_for_the_linear_table(bit_depth: int) -> None:
    lut = PhaseLUT.linear(bit_depth)
    gray = np.arange(lut.levels)
    encoded = phase_to_gray(gray_to_phase(gray, lut), lut)
    assert encoded.dtype == (np.uint8 if bit_depth == 8 else np.int32)
    assert np.array_equal(encoded.astype(np.int64), gray)


def test_widest_gap_is_one_gray_step_or_the_missing_stroke() -> None:
    assert PhaseLUT.linear(8).widest_gap == pytest.approx(2 * math.pi / 256)
    short = PhaseLUT.linear(8, two_pi_gray=256 / 0.88)  # 0.88 x 2 pi: a red laser on a panel made for 600 nm
    assert short.widest_gap == pytest.approx(2 * math.pi - short.phases[-1])
    assert PhaseLUT.linear(8, two_pi_gray=200).widest_gap == pytest.approx(2 * math.pi / 200)  # levels past 2 pi


def test_linear_table_spans_zero_to_two_pi() -> None:
    lut = PhaseLUT.linear()
    assert lut.levels == 256 and lut.bit_depth == 8
    assert lut.phases[0] == 0.0
    assert lut.phases[-1] == pytest.approx(TWO_PI * 255 / 256)
    assert gray_to_phase(np.array([64], dtype=np.uint8), lut).item() == pytest.approx(math.pi / 2)


def test_phase_gray_phase_error_is_at_most_half_a_gray_step() -> None:
    lut = PhaseLUT.linear()
    phase = np.linspace(-3 * math.pi, 5 * math.pi, 100_003)
    error = circular_distance(gray_to_phase(phase_to_gray(phase, lut), lut), phase)
    step = TWO_PI / 256
    assert error.max() <= step / 2 + 1e-6
    assert error.max() > 0.45 * step  # the grid is fine enough to reach the worst case


@pytest.mark.parametrize("span_pi", [1.6, 2.4])
def test_tables_spanning_more_or_less_than_two_pi_pick_the_nearest_level_of_one_period(span_pi: float) -> None:
    lut = PhaseLUT.linear(8, two_pi_gray=256 * 2 / span_pi)
    assert lut.phases[-1] == pytest.approx(span_pi * math.pi * 255 / 256)
    phase = np.linspace(0, TWO_PI, 2_001)[:-1]
    gray = phase_to_gray(phase, lut)
    # Brute force: distance from every phase to every entry of the table's first 2 pi period, modulo 2 pi.
    first_period = lut.phases[lut.phases < lut.phases[0] + TWO_PI]
    all_distances = circular_distance(phase[:, None], first_period[None, :])
    best = all_distances.min(axis=1)
    chosen = circular_distance(gray_to_phase(gray, lut), phase)
    fine_bin = TWO_PI / lut.bins
    assert (chosen <= best + fine_bin).all()


def test_measured_style_table_with_flat_ends() -> None:
    phases = np.concatenate([np.zeros(16), np.linspace(0, 1.9 * math.pi, 224), np.full(16, 1.9 * math.pi)])
    lut = PhaseLUT(phases)
    gray = phase_to_gray(np.array([0.0, math.pi, 1.9 * math.pi]), lut)
    assert gray_to_phase(gray, lut).tolist() == pytest.approx([0.0, math.pi, 1.9 * math.pi], abs=0.02)


def test_bad_tables_are_refused() -> None:
    decreasing = np.linspace(0, TWO_PI, 256)
    decreasing[100] = decreasing[98]
    with pytest.raises(ValueError, match="non-decreasing: gray 100"):
        PhaseLUT(decreasing)
    with pytest.raises(ValueError, match="2\\^bit_depth entries"):
        PhaseLUT(np.linspace(0, TWO_PI, 200))
    with pytest.raises(ValueError, match="NaN"):
        PhaseLUT(np.full(256, np.nan))
    with pytest.raises(ValueError, match="two_pi_gray"):
        PhaseLUT.linear(8, two_pi_gray=0)


def test_gray_to_phase_checks_its_input() -> None:
    lut = PhaseLUT.linear(8)
    with pytest.raises(ValueError, match="integer"):
        gray_to_phase(np.array([1.0]), lut)
    with pytest.raises(ValueError, match="0..255"):
        gray_to_phase(np.array([256]), lut)


def test_encoding_keeps_shape_and_dtype() -> None:
    lut = PhaseLUT.linear()
    phase = np.random.default_rng(0).random((192, 256)) * 20 - 10
    gray = phase_to_gray(phase, lut)
    assert gray.shape == phase.shape and gray.dtype == np.uint8
    assert lut.inverse.size == 1 << 16


_LUTS = {span: PhaseLUT.linear(8, two_pi_gray=256 * 2 / span) for span in (1.6, 2.0, 2.4)}


@settings(max_examples=200, deadline=None)
@given(
    bin_index=st.integers(-(1 << 20), 1 << 20),
    within_bin=st.floats(0.01, 0.99),
    turns=st.integers(-20, 20),
    span_pi=st.sampled_from(sorted(_LUTS)),
)
def test_phase_and_phase_plus_whole_turns_encode_the_same(
    bin_index: int, within_bin: float, turns: int, span_pi: float
) -> None:
    # Phases are kept off the inverse table's bin edges, where rounding alone could pick either side.
    lut = _LUTS[span_pi]
    phase = (bin_index + within_bin) * TWO_PI / lut.bins
    encoded = phase_to_gray(np.array([phase, phase + TWO_PI * turns], dtype=np.float64), lut)
    assert encoded[0] == encoded[1]


@settings(max_examples=100, deadline=None)
@given(gray=st.integers(0, 255), turns=st.integers(-10, 10))
def test_table_phases_plus_whole_turns_decode_to_their_level(gray: int, turns: int) -> None:
    lut = _LUTS[2.0]
    phase = lut.phases[gray] + TWO_PI * turns
    assert phase_to_gray(phase.reshape(1), lut).item() == gray
