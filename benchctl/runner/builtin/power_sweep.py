"""Laser power sweep: per colour, the camera signal against the laser setpoint, to check that the chain is linear
and to find the exposure that uses the sensor's range without saturating at the colour's working setpoint.

The signal is that colour's CFA plane, dark-subtracted, on the image of the ROI (through the stored
registration; the whole active area without one): mean, peak (99.9th percentile) and saturated fraction, all
as fractions of full scale. A straight line through the unsaturated points gives the linearity (R^2 and the
largest deviation); the peak's line at the working setpoint gives the exposure that puts the peak at 80 %.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from msgspec import Meta

from benchctl.capture.exposure import PEAK_PERCENTILE
from benchctl.devices.power import parse_power
from benchctl.profiles import LaserChannel
from benchctl.runner.api import (
    BenchctlError,
    Context,
    Frames,
    HologramParameters,
    Report,
    Step,
    channels,
    check_method,
    exposure_step,
    hologram_step,
    line_plot,
    load_exposure,
    power_w,
    prepared_target,
    shown,
    signal_stats,
    table,
    unknown_setpoints,
)

DESCRIPTION = "camera signal against laser setpoint per colour: linearity and the exposure that does not saturate"


class PowerSweepParameters(HologramParameters, kw_only=True):
    """The target shown and the laser powers it is exposed at ("20mW" or a share of max_power_mw, "25%")."""

    frames: Frames = 1
    target: str = "chart:white"
    levels: Annotated[tuple[str, ...], Meta(min_length=2)] = ("10%", "25%", "50%", "75%", "100%")


PARAMETERS = PowerSweepParameters
PEAK_GOAL = 0.8  # fraction of full scale the recommended exposure puts the peak at


def plan(context: Context) -> list[Step]:
    unknown_setpoints(context)
    params = context.parameters(PowerSweepParameters)
    target = prepared_target(context.profile, params.target, "parameters.target")
    steps: list[Step] = []
    used = channels(context)
    check_method(context, used)
    for channel in used:
        hologram_key = f"hologram/sweep/{channel.name}"
        steps.append(hologram_step(hologram_key, "sweep", target, channel, params))
        for number, watts in enumerate(_levels(context, channel)):
            steps.append(exposure_step(context, f"sweep/{channel.name}/{number}", channel, watts, shown(hologram_key),
                                       f"sweep level {number + 1}"))
    steps.append(Step("report", "linearity fits, exposure advice, report", _reporter(used)))
    return steps


def _levels(context: Context, channel: LaserChannel) -> list[float]:
    levels = []
    for i, text in enumerate(context.parameters(PowerSweepParameters).levels):
        watts = parse_power(text, channel.max_power_mw)
        if watts > channel.max_power_mw * 1e-3 * (1 + 1e-9):
            raise BenchctlError(f"parameters.levels[{i}]: {text} is above {channel.name}'s max_power_mw "
                                f"{channel.max_power_mw:g} mW")
        levels.append(watts)
    return levels


def linear_fit(x: np.ndarray, y: np.ndarray) -> dict[str, float]:
    """Least-squares line y = slope x + offset, with R^2 and the largest deviation relative to the largest y."""
    slope, offset = np.polyfit(x, y, 1)
    fitted = slope * x + offset
    spread = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(np.sum((y - fitted) ** 2)) / spread if spread > 0 else 1.0
    return {"slope": float(slope), "offset": float(offset), "r2": r2,
            "max_deviation": float(np.max(np.abs(y - fitted)) / max(float(np.max(np.abs(y))), 1e-12))}


def _analyse(context: Context, channel: LaserChannel, count: int) -> dict[str, Any]:
    points = []
    for number in range(count):
        key = f"sweep/{channel.name}/{number}"
        image, _ = load_exposure(context, key)
        result = context.result(key)
        points.append({"setpoint_w": result["setpoint_w"], "measured_w": result["measured_w"],
                       **signal_stats(context, image, channel), "exposure_s": _exposure(context, result)})
    usable = [p for p in points if p["saturated_fraction"] == 0.0]
    analysis: dict[str, Any] = {"points": points, "saturated_levels": len(points) - len(usable)}
    if len(usable) < 2:
        analysis["warning"] = (f"{channel.name}: fewer than two unsaturated levels; shorten the exposure or lower "
                               "the levels")
        return analysis
    x = np.array([p["setpoint_w"] for p in usable])
    analysis["mean_fit"] = linear_fit(x, np.array([p["mean"] for p in usable]))
    peak_fit = linear_fit(x, np.array([p["peak"] for p in usable]))
    analysis["peak_fit"] = peak_fit
    working = power_w(context, channel)
    peak_at_working = peak_fit["slope"] * working + peak_fit["offset"]
    exposure = usable[-1]["exposure_s"]
    analysis["working_setpoint_w"] = working
    analysis["peak_at_working"] = peak_at_working
    if exposure and peak_at_working > 0:
        analysis["recommended_exposure_s"] = exposure * PEAK_GOAL / peak_at_working
    return analysis


def _exposure(context: Context, result: dict[str, Any]) -> float | None:
    shots = result.get("camera") or [{}]
    value = shots[0].get("exposure_s")
    if value is None and context.profile.camera is not None:
        value = context.profile.camera.exposure_s
    return value


def _reporter(used: list[LaserChannel]):
    def action(context: Context) -> dict[str, Any]:
        count = len(context.parameters(PowerSweepParameters).levels)
        analyses = {c.name: _analyse(context, c, count) for c in used}
        return power_sweep_report(context, analyses)

    return action


def power_sweep_report(context: Context, analyses: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Signal against setpoint per colour (plot and table), linearity, and the exposure advice."""
    report = Report("Laser power sweep")
    rows, summary = [], []
    for name, analysis in analyses.items():
        for point in analysis["points"]:
            rows.append({"colour": name, "setpoint_mw": point["setpoint_w"] * 1e3,
                         "measured_mw": None if point["measured_w"] is None else point["measured_w"] * 1e3,
                         "mean": point["mean"], "peak": point["peak"],
                         "saturated_fraction": point["saturated_fraction"],
                         "exposure_s": point["exposure_s"]})
        if "warning" in analysis:
            report.warn(analysis["warning"])
            continue
        fit = analysis["mean_fit"]
        summary.append({"colour": name, "R^2": fit["r2"], "max deviation": fit["max_deviation"],
                        "mean per mW": fit["slope"] * 1e-3, "offset": fit["offset"],
                        "working setpoint mW": analysis["working_setpoint_w"] * 1e3,
                        "peak at working setpoint": analysis["peak_at_working"],
                        "recommended exposure s": analysis.get("recommended_exposure_s")})
        if analysis["saturated_levels"]:
            report.warn(f"{name}: {analysis['saturated_levels']} level(s) saturated (left out of the fits)")
        if analysis["peak_at_working"] >= 1.0:
            report.warn(f"{name}: the working setpoint saturates the sensor at this exposure")
    series = {name: ([p["setpoint_w"] * 1e3 for p in a["points"]], [p["mean"] for p in a["points"]])
              for name, a in analyses.items()}
    report.section("Signal against setpoint", line_plot(series, "setpoint (mW)", "mean signal (full scale = 1)"))
    report.section("Linearity and exposure", table(summary), "<p>Fits use the unsaturated levels. The recommended "
                   f"exposure puts the peak ({PEAK_PERCENTILE:g}th percentile) at {PEAK_GOAL:.0%} of full scale at "
                   "the working setpoint.</p>")
    report.section("Measurements", table(rows))
    headline = [f"{s['colour']}: R^2 {s['R^2']:.5f}, recommended exposure "
                + (f"{s['recommended exposure s']:.4g} s" if s["recommended exposure s"] else "n/a")
                for s in summary]
    return report.write(context, {"procedure": "power-sweep", "colours": analyses}, rows, list(analyses),
                        headline + report.warnings)
