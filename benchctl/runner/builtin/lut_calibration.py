"""SLM lookup-table calibration: per colour, the SLM's gray -> phase response measured with the camera.

A binary grating of period 2 px (gray 0 / gray g) sends its first orders to the edge of the SLM's frequency
band, where the Fourier iris stops them; the zero order that reaches the camera has intensity a + b cos(dphi(g)).
Measured on a subset of gray levels, inverted and unwrapped (benchctl.capture.lut_calibration), interpolated
to every level, the table is written as calibration/<profile>/lut-<colour>.csv, which later runs use for every
channel whose table the profile does not name. On the simulated bench it is compared with the simulator's truth.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from msgspec import Meta

from benchctl.capture.lut_calibration import (
    calibration_grays,
    grating_frame,
    lut_from_response,
    phase_response,
    zero_order_signal,
)
from benchctl.devices.slm.lut import save_lut
from benchctl.profiles import LaserChannel
from benchctl.runner.api import (
    Calibration,
    Context,
    DarkFrames,
    ExposureParameters,
    Frames,
    Report,
    Step,
    channels,
    exposure_step,
    line_plot,
    load_exposure,
    power_w,
    table,
    target_plane,
    unknown_setpoints,
)

DESCRIPTION = "gray -> phase response per colour from zero-order intensity of binary gratings; writes the LUTs"


class LutCalibrationParameters(ExposureParameters, kw_only=True):
    """One frame, no dark, per grating: the zero order is bright and the fit uses many gray levels."""

    frames: Frames = 1
    dark_frames: DarkFrames = 0
    gray_step: Annotated[int, Meta(ge=1)] = 8  # every n-th gray level (and the last)


PARAMETERS = LutCalibrationParameters


def plan(context: Context) -> list[Step]:
    unknown_setpoints(context)
    used = channels(context)
    steps = lut_steps(context, used, context.parameters(LutCalibrationParameters))
    return steps + [Step("report", "lookup-table report", _reporter(used))]


def lut_steps(context: Context, used: list[LaserChannel], params: LutCalibrationParameters) -> list[Step]:
    """Grating exposures and the fit per colour; colour capture runs these first for uncalibrated colours."""
    slm = context.profile.require("slm", "optics").slm
    assert slm is not None
    grays = calibration_grays(slm.bit_depth, params.gray_step)
    steps: list[Step] = []
    for channel in used:
        watts = power_w(context, channel)
        for gray in grays:
            steps.append(exposure_step(context, f"lut/{channel.name}/{gray}", channel, watts,
                                       _grating(slm.shape, slm.bit_depth, gray), f"grating 0/{gray}",
                                       frames=params.frames, dark_frames=params.dark_frames))
        steps.append(Step(f"lut/{channel.name}/fit", f"phase response and lookup table ({channel.name})",
                          _fitter(channel, grays)))
    return steps


def _grating(shape: tuple[int, int], bit_depth: int, gray: int):
    return lambda context: grating_frame(shape, gray, bit_depth=bit_depth)


def _fitter(channel: LaserChannel, grays: list[int]):
    def action(context: Context) -> dict[str, Any]:
        slm = context.profile.slm
        assert slm is not None
        registration = context.calibration.registrations().get(channel.name)
        homography = None if registration is None else np.asarray(registration["homography"])
        signals = []
        for gray in grays:
            image, _ = load_exposure(context, f"lut/{channel.name}/{gray}")
            signals.append(zero_order_signal(image, target_plane(channel), homography, slm.shape))
        phases = phase_response(np.array(grays), np.array(signals))
        lut = lut_from_response(np.array(grays), phases, slm.bit_depth)
        run = context.record.name if context.record else None

        def store(calibration: Calibration) -> None:
            save_lut(calibration.lut_path(channel.name), lut)
            calibration.record_lut(channel.name, {"grays": len(grays), "run": run})

        context.save_calibration(store)
        measured = lut.phases
        result: dict[str, Any] = {"grays": grays, "signals": signals, "phases": [float(p) for p in phases],
                  "depth_rad": float(measured[-1] - measured[0]),
                  "file": context.calibration.lut_path(channel.name).name}
        truth = context.slm.ground_truth_lut(channel.wavelength_m)  # None on a real panel
        if truth is not None:
            error = measured - measured[0] - (truth - truth[0])
            one_period = truth - truth[0] <= 2 * np.pi
            result["simulator"] = {"rms_rad": float(np.sqrt(np.mean(error[one_period] ** 2))),
                                   "max_rad": float(np.abs(error[one_period]).max())}
        context.say(f"      {channel.name}: phase depth {result['depth_rad']:.3f} rad"
                    + (f", RMS {result['simulator']['rms_rad']:.4f} rad from the simulator's truth" if truth is not None
                       else ""))
        return result

    return action


def _reporter(used: list[LaserChannel]):
    def action(context: Context) -> dict[str, Any]:
        return lut_report(context, {c.name: context.result(f"lut/{c.name}/fit") for c in used})

    return action


def lut_report(context: Context, fits: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Measured gray -> phase per colour (plot), depth, and on the simulated bench the error against the truth."""
    series = {name: ([float(g) for g in fit["grays"]], fit["phases"]) for name, fit in fits.items()}
    rows = [{"colour": name, "grays measured": len(fit["grays"]), "phase depth rad": fit["depth_rad"],
             "RMS vs simulator rad": (fit.get("simulator") or {}).get("rms_rad"),
             "max vs simulator rad": (fit.get("simulator") or {}).get("max_rad"), "table": fit["file"]}
            for name, fit in fits.items()]
    signals = {name: ([float(g) for g in fit["grays"]], fit["signals"]) for name, fit in fits.items()}
    report = Report("SLM lookup-table calibration")
    report.section("Measured phase response", line_plot(series, "gray level", "phase - phase(0) (rad)"))
    report.section("Zero-order signal", line_plot(signals, "gray level", "signal (full scale = 1)"))
    report.section("Tables", table(rows), "<p>The tables are stored per profile and used by later runs for every "
                   "channel whose table the profile does not name ([slm.lut]).</p>")
    headline = [f"{r['colour']}: depth {r['phase depth rad']:.3f} rad"
                + (f", RMS {r['RMS vs simulator rad']:.4f} rad vs the simulator"
                   if r["RMS vs simulator rad"] is not None else "") for r in rows]
    return report.write(context, {"procedure": "lut-calibration", "colours": fits}, rows, list(fits), headline)
