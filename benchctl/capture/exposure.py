"""Automatic exposure: the laser power that puts a colour's brightest pixels at a chosen fraction of full scale.

The camera signal is linear in laser power (the power-sweep procedure checks this; R^2 > 0.9999 on the
simulated bench), so one probe frame at a known power predicts the power for any peak. The camera's exposure
time is left alone: changing it needs property writes a camera may refuse, while every laser takes setpoints.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

PEAK_PERCENTILE = 99.9
"""Percentile taken as a plane's peak, so a single hot pixel does not count as signal: "peak" means the brightest
0.1 % everywhere benchctl says it (reports, automatic exposure, `camera show`, which names the brightest pixel
apart)."""
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
