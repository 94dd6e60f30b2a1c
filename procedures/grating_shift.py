"""Example of a Python procedure: how far a blazed grating moves each colour's image, against the prediction.

A linear phase ramp of period P pixels tilts the light by lambda / (P pitch), so at the target plane (distance z)
the image moves by z lambda / (P pitch^2) target-plane pixels. The procedure computes a hologram of a Siemens star
(the procedure's method, DPAC by default), shows it without and with the ramp added, exposes each colour alone,
registers both captures onto the target plane (the stored camera-SLM registration) and measures the shift between
them by phase correlation.

    benchctl run procedures/grating_shift.py [--profile P]

Written on the procedure API (`benchctl.runner.api`), as the built-in procedures are: DESCRIPTION, PARAMETERS and
plan(context) -> list[Step].
"""

from __future__ import annotations

import math
from typing import Annotated, Any

import cv2
import msgspec
import numpy as np

from benchctl.runner.api import (BenchctlError, Context, HologramParameters, Report, Step, channels, displayed_frame,
                                 exposure_step, hologram_step, load_exposure, power_w, prepared_target, registered,
                                 shown, table, unregistered)

DESCRIPTION = "blazed-grating deflection per colour, measured through the registration, against z lambda / (P pitch)"


class GratingShiftParameters(HologramParameters, kw_only=True):
    period_px: Annotated[float, msgspec.Meta(gt=2)] = 32.0  # of the blazed grating


PARAMETERS = GratingShiftParameters


def plan(context: Context) -> list[Step]:
    used = channels(context)
    missing = unregistered(context, used)
    if missing:
        raise BenchctlError(f"no stored camera-SLM registration for {', '.join(c.name for c in missing)}: run "
                            "procedures/registration.toml first")
    star = prepared_target(context.profile, "chart:siemens")
    period = context.parameters(GratingShiftParameters).period_px
    steps = []
    for channel in used:
        star_key = f"hologram/{channel.name}"
        steps.append(hologram_step(star_key, "siemens", star, channel))
        steps.append(exposure_step(context, f"flat/{channel.name}", channel, power_w(context, channel),
                                   shown(star_key), "expose the star"))
        steps.append(exposure_step(context, f"grating/{channel.name}", channel, power_w(context, channel),
                                   _with_ramp(star_key, channel.name, period), "expose the star through the grating"))
    steps.append(Step("report", "shifts against the prediction", _analyse))
    return steps


def _with_ramp(star_key: str, channel: str, period: float):
    """The star's frame with a phase ramp of `period` pixels along the columns added."""
    def frame(context: Context) -> np.ndarray:
        phase = context.decode(displayed_frame(context, star_key), channel)
        return context.encode(phase + 2 * math.pi * np.arange(phase.shape[1]) / period, channel)

    return frame


def _analyse(context: Context) -> dict[str, Any]:
    period = context.parameters(GratingShiftParameters).period_px
    rows = []
    for channel in channels(context):
        flat, tilted = (registered(context, load_exposure(context, f"{name}/{channel.name}")[0], channel)
                        for name in ("flat", "grating"))
        window = cv2.createHanningWindow(flat.shape[::-1], cv2.CV_64F)
        shift, _ = cv2.phaseCorrelate(flat.astype(np.float64), tilted.astype(np.float64), window)
        setup = context.setup(channel.name)
        predicted = setup.distance_m * setup.wavelength_m / (period * setup.pitch_m[1] ** 2)
        rows.append({"colour": channel.name, "predicted_px": predicted, "measured_px": float(shift[0]),
                     "across_px": float(shift[1]), "error_px": float(shift[0]) - predicted})
    report = Report("Blazed-grating shift")
    report.section("Shift of each colour", table(rows))
    return report.write(context, {"procedure": "grating-shift", "colours": rows}, rows, [r["colour"] for r in rows],
                        [f"{r['colour']}: shift {r['measured_px']:.2f} px, predicted {r['predicted_px']:.2f} px"
                         for r in rows])
