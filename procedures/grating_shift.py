"""Example of a Python procedure: how far a blazed grating moves each colour's image, against the prediction.

A linear phase ramp of period P pixels tilts the light by lambda / (P pitch), so at the target plane (distance z)
the image moves by z lambda / (P pitch^2) target-plane pixels. The procedure shows a DPAC hologram of a Siemens star
without and with the ramp added, exposes each colour alone, registers both captures onto the target plane (the
stored camera-SLM registration) and measures the shift between them by phase correlation.

    benchctl run procedures/grating_shift.py [--profile P]

A Python procedure defines DESCRIPTION, PARAMETERS (a model deriving from benchctl.runner.procedure.Parameters, here
the shared exposure parameters plus its own) and plan(context) -> list[Step]; the built-in procedures in
benchctl/runner/builtin/ are written the same way.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np

import cv2
import msgspec
import torch

from benchctl.capture.colour_planes import registered_plane
from benchctl.cgh import get_method
from benchctl.cgh.method import wrap_phase
from benchctl.errors import BenchctlError
from benchctl.files import write_csv, write_json
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import LaserChannel
from benchctl.runner.holograms import target_plane
from benchctl.runner.procedure import Context, Step
from benchctl.runner.report import table, write_report
from benchctl.runner.steps import (
    ExposureParameters,
    channels,
    exposure_step,
    load_exposure,
    power_w,
    prepared_target,
)

DESCRIPTION = "blazed-grating deflection per colour, measured through the registration, against z lambda / (P pitch)"


class GratingShiftParameters(ExposureParameters, kw_only=True):
    period_px: Annotated[float, msgspec.Meta(gt=2)] = 32.0  # of the blazed grating


PARAMETERS = GratingShiftParameters


def plan(context: Context) -> list[Step]:
    registrations = context.calibration.registrations()
    steps = []
    for channel in channels(context):
        if channel.name not in registrations:
            raise BenchctlError(f"no stored camera-SLM registration for {channel.name}: run "
                                "procedures/registration.toml first")
        for name, period in (("flat", 0.0), ("grating", context.parameters(GratingShiftParameters).period_px)):
            steps.append(exposure_step(context, f"{name}/{channel.name}", (name, channel.name), channel,
                                       power_w(context, channel), _ramp(period, channel), f"expose {name}"))
    steps.append(Step("report", "centroids, shifts against the prediction", _analyse))
    return steps


def _ramp(period: float, channel: LaserChannel):
    """The SLM frame of a DPAC hologram of chart:siemens for `channel`, plus a phase ramp along the columns of
    `period` pixels (0: no ramp), encoded for the channel."""
    def frame(context: Context) -> np.ndarray:
        setup = OpticalSetup.from_profile(context.profile, channel.name)
        target = prepared_target(context.profile, "chart:siemens")[target_plane(channel)]
        phase = get_method("dpac")(target, setup)
        if period:
            phase = phase + 2 * math.pi * torch.arange(setup.shape[1]) / period
        return context.bench.slm.encode(wrap_phase(phase), channel.name)

    return frame


def _registered(context: Context, key: str, channel: LaserChannel) -> np.ndarray:
    """The capture of `key` on the target plane's ROI (through the stored registration)."""
    profile = context.profile
    assert profile.slm is not None and profile.optics is not None
    image, _ = load_exposure(context, key)
    homography = np.asarray(context.calibration.registrations()[channel.name]["homography"])
    return registered_plane(image, target_plane(channel), homography, profile.slm.shape, profile.optics.roi)


def _analyse(context: Context) -> dict[str, Any]:
    profile = context.profile
    assert profile.slm is not None and profile.optics is not None
    rows = []
    for channel in channels(context):
        flat = _registered(context, f"flat/{channel.name}", channel).astype(np.float64)
        tilted = _registered(context, f"grating/{channel.name}", channel).astype(np.float64)
        window = cv2.createHanningWindow(flat.shape[::-1], cv2.CV_64F)
        shift, _ = cv2.phaseCorrelate(flat, tilted, window)
        predicted = (profile.optics.distance_mm * 1e-3 * channel.wavelength_m
                     / (context.parameters(GratingShiftParameters).period_px * profile.slm.pitch_m ** 2))
        rows.append({"colour": channel.name, "predicted_px": predicted, "measured_px": float(shift[0]),
                     "across_px": float(shift[1]), "error_px": float(shift[0]) - predicted})
    write_json(context.path("metrics.json"), {"procedure": "grating-shift", "colours": rows})
    write_csv(context.path("metrics.csv"), rows)
    write_report(context, "Blazed-grating shift", f"<h2>Shift of each colour</h2>{table(rows)}",
                 [r["colour"] for r in rows], [])
    return {"headline": [f"{r['colour']}: shift {r['measured_px']:.2f} px, predicted {r['predicted_px']:.2f} px"
                         for r in rows]}
