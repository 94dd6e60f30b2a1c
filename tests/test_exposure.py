"""Automatic exposure: the power that brings a measured peak to the goal, within the laser's limit."""

from __future__ import annotations

import pytest

from benchctl.capture.exposure import SATURATED_BACKOFF, choose_power


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
