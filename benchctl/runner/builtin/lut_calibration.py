"""SLM lookup-table calibration: per colour, the SLM's gray -> phase response measured with the camera.

A binary grating of period 2 px (gray 0 / gray g) sends its first orders to the edge of the SLM's frequency
band, where the Fourier iris stops them; the zero order that reaches the camera has intensity a + b cos(dphi(g)).
Measured on a subset of gray levels, inverted and unwrapped (benchctl.capture.lut_calibration), interpolated
to every level, the table is written as calibration/<profile>/lut-<colour>.csv, which later runs use for every
channel whose table the profile does not name, if it passes its acceptance test (calibration.acceptance): the gray-0
grating's signal shows light, a table could be read from the curve, and the curve a + b cos(phase(g)) of the new
table follows the measured signals within MAX_MISFIT of their span and no worse than the table in use did. On the
simulated bench it is compared with the simulator's truth.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from msgspec import Meta

from benchctl.capture.lut_calibration import (
    CalibrationError,
    calibration_grays,
    grating_frame,
    lut_from_response,
    phase_response,
    zero_order_signal,
)
from benchctl.devices.slm.lut import lut_for, save_lut
from benchctl.files import write_json
from benchctl.optics import PhaseLUT
from benchctl.profiles import LaserChannel
from benchctl.runner.api import (
    Calibration,
    Context,
    DarkFrames,
    ExposureParameters,
    Frames,
    Report,
    Step,
    Verdict,
    channels,
    exposure_step,
    line_plot,
    load_exposure,
    power_w,
    row,
    table,
    target_plane,
    unknown_setpoints,
)

MIN_SIGNAL = 0.003  # the gray-0 grating's zero order (the brightest) reaches this fraction of full scale: light
MAX_MISFIT = 0.05  # RMS of the signals about the new table's curve, as a fraction of their span
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


def signal_misfit(grays: list[int], signals: list[float], lut: PhaseLUT) -> float:
    """How far the measured zero-order signals lie from the curve a + b cos(phase(g) - phase(0)) that `lut` predicts
    (a, b fitted by least squares): RMS as a fraction of the signals' span. A table read from these signals follows
    them up to its smoothing; the table it replaces shows how far the panel has moved from it."""
    values = np.asarray(signals, dtype=np.float64)
    phases = lut.phases[np.asarray(grays)]
    basis = np.stack([np.ones(len(values)), np.cos(phases - phases[0])], axis=1)
    coefficients = np.linalg.lstsq(basis, values, rcond=None)[0]
    span = float(values.max() - values.min())
    return float(np.sqrt(np.mean((basis @ coefficients - values) ** 2)) / span) if span > 0 else float("inf")


def _fitter(channel: LaserChannel, grays: list[int]):
    def action(context: Context) -> dict[str, Any]:
        slm = context.profile.slm
        assert slm is not None
        registration = context.calibration.registrations().get(channel.name)
        homography = None if registration is None else np.asarray(registration["homography"])
        signals, problem = [], None
        try:
            for gray in grays:
                image, _ = load_exposure(context, f"lut/{channel.name}/{gray}")
                signals.append(zero_order_signal(image, target_plane(channel), homography, slm.shape))
            phases = phase_response(np.array(grays), np.array(signals))
            lut = lut_from_response(np.array(grays), phases, slm.bit_depth)
        except CalibrationError as exc:
            phases, lut, problem = None, None, str(exc)
        old = lut_for(slm, channel.name)  # the table in use: the stored one, the profile's, else linear
        complete = len(signals) == len(grays)
        verdict = Verdict("lookup table", channel.name, "signal misfit",
                          None if lut is None else round(signal_misfit(grays, signals, lut), 5),
                          round(signal_misfit(grays, signals, old), 5) if complete else None,
                          details={"signal": round(signals[0], 6) if signals else None,
                                   "replaces": "stored" if channel.name in context.calibration.lut_files()
                                   else "profile's" if channel.name in slm.lut else "linear"})
        if signals:
            verdict.check(signals[0] >= MIN_SIGNAL, f"no light reached the camera: the gray-0 grating's zero order at "
                                                    f"{signals[0]:.2%} of full scale, below {MIN_SIGNAL:.1%}")
        if problem is not None:
            verdict.check(False, f"no table could be read: {problem}")
            return {"grays": grays[:len(signals)], "signals": signals, "problem": problem,
                    "calibration": context.store_calibration(verdict, lambda calibration: None, {})}
        assert lut is not None and phases is not None
        misfit = signal_misfit(grays, signals, lut)
        verdict.check(misfit <= MAX_MISFIT, f"signal misfit {misfit:.4g} of the span, above the bound {MAX_MISFIT:g}")
        verdict.no_worse()
        run = context.record.name if context.record else None

        def store(calibration: Calibration) -> None:
            save_lut(calibration.lut_path(channel.name), lut)
            calibration.record_lut(channel.name, {"grays": len(grays), "run": run})

        record = context.store_calibration(verdict, store, {
            f"lut-{channel.name}.csv": lambda path: save_lut(path, lut),
            f"lut-{channel.name}.json": lambda path: write_json(path, {"grays": grays, "signals": signals,
                                                                       "acceptance": verdict.record(False, [])})})
        measured = lut.phases
        result: dict[str, Any] = {"grays": grays, "signals": signals, "phases": [float(p) for p in phases],
                  "depth_rad": float(measured[-1] - measured[0]), "calibration": record,
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


def lut_sections(report: Report, fits: dict[str, dict[str, Any]]) -> tuple[list[str], list[dict[str, Any]]]:
    """The lookup tables' sections of a report (their own, or a procedure's that measured them first): whether each
    table was stored, the measured gray -> phase response and zero-order signal per colour, depth, and on the
    simulated bench the error against the truth. Returns headline lines and the table's rows."""
    measured = {name: fit for name, fit in fits.items() if "phases" in fit}
    series = {name: ([float(g) for g in fit["grays"]], fit["phases"]) for name, fit in measured.items()}
    rows: list[dict[str, Any]] = [
        {"colour": name, "grays measured": len(fit["grays"]), "phase depth rad": fit.get("depth_rad"),
         "RMS vs simulator rad": (fit.get("simulator") or {}).get("rms_rad"),
         "max vs simulator rad": (fit.get("simulator") or {}).get("max_rad"),
         "table": fit["file"] if fit["calibration"]["stored"] else "not stored"} for name, fit in fits.items()]
    signals = {name: ([float(g) for g in fit["grays"]], fit["signals"]) for name, fit in fits.items()}
    report.calibrations([fit["calibration"] for fit in fits.values()])
    report.section("SLM lookup tables", table(rows), row(
        line_plot(series, "gray level", "measured phase - phase(0) (rad)"),
        line_plot(signals, "gray level", "zero-order signal (full scale = 1)")),
        "<p>The tables are stored per profile and used by later runs for every channel whose table the profile "
        "does not name ([slm.lut]).</p>")
    headline = [f"{r['colour']}: " + ("no table" if r["phase depth rad"] is None else
                                      f"depth {r['phase depth rad']:.3f} rad")
                + (f", RMS {r['RMS vs simulator rad']:.4f} rad vs the simulator"
                   if r["RMS vs simulator rad"] is not None else "")
                + ("" if fits[r["colour"]]["calibration"]["stored"] else "; NOT stored") for r in rows]
    return headline, rows


def lut_report(context: Context, fits: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The lookup-table calibration's report (`lut_sections`)."""
    report = Report("SLM lookup-table calibration")
    headline, rows = lut_sections(report, fits)
    return report.write(context, {"procedure": "lut-calibration", "colours": fits}, rows, list(fits), headline)
