"""Automatic exposure: the power that brings a measured peak to the goal, within the laser's limit; frames of an
exposure-free measure kept between noise and saturation."""

from __future__ import annotations

import numpy as np
import pytest

from benchctl.capture.exposure import SATURATED_BACKOFF, STUCK_PIXELS, brightest, choose_power, clipped, kept_in_range
from benchctl.errors import BenchctlError


def test_power_scales_the_peak_linearly_to_the_goal() -> None:
    choice = choose_power(2e-3, 0.05, False, 0.7, 40e-3)
    assert choice.power_w == pytest.approx(2e-3 * 0.7 / 0.05) and not choice.limited_by_max
    lower = choose_power(40e-3, 0.9, False, 0.7, 40e-3)
    assert lower.power_w == pytest.approx(40e-3 * 0.7 / 0.9)


def test_power_never_exceeds_the_channels_max() -> None:
    choice = choose_power(1e-3, 0.001, False, 0.7, 40e-3)
    assert choice.power_w == 40e-3 and choice.limited_by_max
    dark = choose_power(1e-3, 0.0, False, 0.7, 40e-3)
    assert dark.power_w == 40e-3 and dark.limited_by_max is False  # wanted exactly max: nothing to scale


def test_a_saturated_probe_backs_off_instead_of_trusting_its_clipped_peak() -> None:
    choice = choose_power(20e-3, 1.0, True, 0.7, 40e-3)
    assert choice.power_w == pytest.approx(20e-3 * SATURATED_BACKOFF) and choice.probe_saturated


@pytest.mark.parametrize("goal", [0.0, 1.0, -0.5])
def test_goal_must_be_a_fraction(goal: float) -> None:
    with pytest.raises(ValueError, match="peak goal"):
        choose_power(1e-3, 0.5, False, goal, 40e-3)


def camera(level_per_w: float, log: list[float]):
    """A linear camera whose brightest pixel reads `level_per_w` x power, clipping at full scale."""
    def take(power: float) -> tuple[float, bool, str]:
        log.append(power)
        level = level_per_w * power
        return min(level, 1.0), level >= 1.0, f"frame at {power:g}"
    return take


def test_a_frame_that_saturates_is_retaken_lower_until_it_is_in_range() -> None:
    log: list[float] = []
    value, power = kept_in_range(camera(25_000.0, log), 40e-3, 40e-3)  # 1000 x full scale at the setpoint
    assert 0.1 <= 25_000.0 * power < 1.0 and log[-1] == power and value == f"frame at {power:g}"
    assert log[:5] == pytest.approx([40e-3 * SATURATED_BACKOFF**k for k in range(5)])  # two stops down per try
    assert len(log) <= 7


def test_a_dim_frame_is_retaken_higher_but_never_above_the_maximum() -> None:
    log: list[float] = []
    _, power = kept_in_range(camera(20.0, log), 1e-3, 40e-3)  # 2 % of full scale at 1 mW
    assert power == pytest.approx(0.5 / 20.0) and len(log) == 2  # the ratio to the goal, one retake
    log.clear()
    _, power = kept_in_range(camera(0.5, log), 1e-3, 40e-3)  # dim even at the maximum: kept there
    assert power == 40e-3 and len(log) == 2
    log.clear()
    _, power = kept_in_range(camera(5.0, log), 0.1, 40e-3)  # in range as it came: not retaken
    assert power == 0.1 and len(log) == 1


def test_a_retake_stays_between_the_powers_that_were_dim_and_saturated() -> None:
    log: list[float] = []

    def cliff(power: float) -> tuple[float, bool, None]:  # reads 1 % below 1 mW and clips from there on
        log.append(power)
        return (0.01, False, None) if power < 1e-3 else (1.0, True, None)

    with pytest.raises(BenchctlError, match=r"no laser power kept a frame between 5% of full scale and saturation in "
                                            r"12 tries \(the last at 0.999 mW\): shorten the camera's exposure_s"):
        kept_in_range(cliff, 4e-3, 40e-3)
    assert len(log) == 12
    for k in range(2, 12):  # once bracketed, each try lies strictly between the dim and the saturated powers so far
        dim = max((p for p in log[:k] if p < 1e-3), default=0.0)
        clipping = min(p for p in log[:k] if p >= 1e-3)
        assert dim < log[k] < clipping or not dim


def test_brightest_leaves_out_a_few_stuck_pixels() -> None:
    mosaic = np.zeros((64, 64), np.float32)
    saturated = np.zeros(mosaic.shape, bool)
    hot = (np.arange(STUCK_PIXELS), np.arange(STUCK_PIXELS))
    mosaic[hot], saturated[hot] = 1.0, True
    mosaic[40, 40:43] = 0.3
    assert brightest(mosaic) == pytest.approx(0.3) and clipped(saturated) is False
    saturated[50, 50] = True
    assert clipped(saturated) is True
