"""Automatic exposure: the laser power that puts a colour's brightest pixels at a chosen fraction of full scale.

The camera signal is linear in laser power (the power-sweep procedure checks this; R^2 > 0.9999 on the
simulated bench), so one probe frame at a known power predicts the power for any peak. The camera's exposure
time is left alone: changing it needs property writes a camera may refuse, while every laser takes setpoints.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import TypeVar

import numpy as np

from benchctl.errors import BenchctlError

PEAK_PERCENTILE = 99.9
"""Percentile taken as a plane's peak, so a single hot pixel does not count as signal: "peak" means the brightest
0.1 % everywhere benchctl says it (reports, automatic exposure, `camera show`, which names the brightest pixel
apart)."""
STUCK_PIXELS = 8
"""Pixels a frame's brightest level and its saturation test leave out (hot or stuck pixels, not light): where a few dots
hold the light, the 99.9th percentile would miss them, so `brightest` counts pixels instead."""
SATURATED_BACKOFF = 0.25
"""Power factor after a saturated probe: its peak reads full scale whatever the true value, so the ratio
goal / peak would overestimate the power; a quarter moves at least two stops down."""


@dataclass(frozen=True)
class ExposureChoice:
    """What automatic exposure decided for one colour, and why (kept in the run's step log)."""

    probe_w: float
    probe_peak: float  # fraction of full scale, 99.9th percentile of the colour's pixels on the ROI
    probe_saturated: bool
    goal: float
    power_w: float
    limited_by_max: bool

    def as_dict(self) -> dict[str, float | bool]:
        return asdict(self)


def choose_power(probe_w: float, probe_peak: float, saturated: bool, goal: float, max_w: float) -> ExposureChoice:
    """The power that brings the peak from `probe_peak` (measured at `probe_w`) to `goal`, never above max_w.

    A probe with no signal at all (peak <= 0) gives max_w: nothing to scale, and more light is the only way on.
    """
    if not 0 < goal < 1:
        raise ValueError(f"peak goal must be a fraction of full scale in (0, 1), got {goal}")
    if probe_w <= 0:
        raise ValueError(f"probe power must be positive, got {probe_w} W")
    if saturated:
        wanted = probe_w * SATURATED_BACKOFF
    elif probe_peak <= 0:
        wanted = max_w
    else:
        wanted = probe_w * goal / probe_peak
    power = min(wanted, max_w)
    return ExposureChoice(probe_w, probe_peak, saturated, goal, power, limited_by_max=wanted > max_w)


def brightest(mosaic: np.ndarray) -> float:
    """A frame's brightest level (fraction of full scale) apart from its STUCK_PIXELS brightest pixels."""
    values = mosaic.ravel()
    rank = values.size - 1 - min(STUCK_PIXELS, values.size - 1)
    return float(np.partition(values, rank)[rank])


def clipped(saturated: np.ndarray) -> bool:
    """Whether more than STUCK_PIXELS pixels of a frame saturate."""
    return int(np.count_nonzero(saturated)) > STUCK_PIXELS


Taken = TypeVar("Taken")


def kept_in_range(take: Callable[[float], tuple[float, bool, Taken]], power_w: float, max_w: float, *,
                  low: float = 0.05, goal: float = 0.5, tries: int = 12) -> tuple[Taken, float]:
    """A frame for a measure that does not depend on exposure (a sweep's sharpness), taken again until it neither
    saturates nor reads below `low` of full scale (unless already at `max_w`): through focus the brightest pixel moves
    by orders of magnitude, and a clipped focus flattens the very peak the sweep looks for.

    take(power) captures at `power` and returns (brightest level, saturated, value). Each retake's power lies between
    the highest that read dim and the lowest that saturated. Returns (value, power used)."""
    dim_w, saturated_w = 0.0, math.inf
    for _ in range(tries):
        level, saturated, value = take(power_w)
        if saturated:
            saturated_w = power_w
            wanted = math.sqrt(dim_w * saturated_w) if dim_w else power_w * SATURATED_BACKOFF
        elif level < low and power_w < max_w:
            dim_w = power_w
            wanted = min(power_w * goal / level if level > 0 else max_w, max_w)
            if wanted >= saturated_w:
                wanted = math.sqrt(dim_w * saturated_w)
        else:
            return value, power_w
        power_w = wanted
    raise BenchctlError(f"no laser power kept a frame between {low:.0%} of full scale and saturation in {tries} "
                        f"tries (the last at {power_w * 1e3:.3g} mW): shorten the camera's exposure_s or lower its iso")
