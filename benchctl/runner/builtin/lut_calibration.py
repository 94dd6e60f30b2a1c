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
from benchctl.devices.slm import slm_for
from benchctl.devices.slm.lut import save_lut
from benchctl.profiles import LaserChannel
from benchctl.runner.calibration import Calibration
from benchctl.runner.holograms import target_plane
from benchctl.runner.procedure import Context, Step
from benchctl.runner.report import lut_report
from benchctl.runner.steps import (
    DarkFrames,
    ExposureParameters,
    Frames,
    channels,
    exposure_step,
    load_exposure,
    power_w,
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
            steps.append(exposure_step(context, f"lut/{channel.name}/{gray}", ("lut", channel.name, f"gray-{gray:05d}"),
                                       channel, watts, _grating(gray), f"grating 0/{gray}", frames=params.frames,
                                       dark_frames=params.dark_frames))
        steps.append(Step(f"lut/{channel.name}/fit", f"phase response and lookup table ({channel.name})",
                          _fitter(channel, grays)))
    return steps


def _grating(gray: int):
    def frame(context: Context) -> np.ndarray:
        slm = context.bench.slm
        return grating_frame(slm.shape, gray, bit_depth=slm.bit_depth)

    return frame


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
        for calibration in (context.calibration, Calibration.store(context.calibration.profile)):
            save_lut(calibration.lut_path(channel.name), lut)
            calibration.record_lut(channel.name, {"grays": len(grays), "run": context.record.name if context.record
                                                  else None})
        context.recalibrated()
        table = lut.phases
        result = {"grays": grays, "signals": signals, "phases": [float(p) for p in phases],
                  "depth_rad": float(table[-1] - table[0]), "file": f"calibration/lut-{channel.name}.csv"}
        truth = slm_for(context.profile).ground_truth_lut(channel.wavelength_m)  # None on a real panel
        if truth is not None:
            error = table - table[0] - (truth - truth[0])
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
