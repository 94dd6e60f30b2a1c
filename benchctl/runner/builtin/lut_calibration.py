"""SLM lookup-table calibration: per colour, the SLM's gray -> phase response measured with the camera.

A binary grating of period 2 px (gray 0 / gray g) sends its first orders to the edge of the SLM's frequency
band, where the Fourier iris stops them; the zero order that reaches the camera has intensity a + b cos(dphi(g)).
Measured on a subset of gray levels, inverted and unwrapped (benchctl.capture.lut_calibration), interpolated
to every level, the table is written as calibration/<profile>/lut-<colour>.csv, which later runs use for every
channel whose table the profile does not name, if it passes its acceptance test (calibration.acceptance): the gray-0
grating's signal shows light, a table could be read from the curve, and the table predicts gray levels it was not
read from within MAX_MISFIT of the signals' span and no worse than the table in use does (`held_out_misfit`: a table
read from all the signals follows them by construction). On the simulated bench it is compared with the simulator's
truth.
"""

from __future__ import annotations

from collections.abc import Callable
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
MAX_MISFIT = 0.05  # RMS of the held-out signals about the table's curve, as a fraction of their span
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


def held_out_misfit(grays: list[int], signals: list[float], table_for: Callable[[list[int]], PhaseLUT]) -> float:
    """How well a table predicts zero-order signals it was not read from, in two folds: the measured levels between the
    first and the last are split alternately; each half is held out in turn, `table_for(kept)` gives the table from
    the other levels (the indices `kept`: a new table read from them, or the table in use whatever they are), the
    curve a + b cos(phase(g) - phase(0)) is fitted to the kept signals (least squares) and predicts the held-out
    ones. RMS of the predictions' errors as a fraction of the signals' span."""
    values = np.asarray(signals, dtype=np.float64)
    inner = list(range(1, len(grays) - 1))
    errors = []
    for held in (inner[0::2], inner[1::2]):
        kept = [k for k in range(len(grays)) if k not in held]
        table = table_for(kept)
        basis = np.stack([np.ones(len(values)), np.cos(table.phases[np.asarray(grays)] - table.phases[0])], axis=1)
        coefficients = np.linalg.lstsq(basis[kept], values[kept], rcond=None)[0]
        errors.extend(basis[held] @ coefficients - values[held])
    span = float(values.max() - values.min())
    return float(np.sqrt(np.mean(np.square(errors))) / span) if span > 0 and errors else float("inf")


def _table(grays: list[int], signals: list[float], kept: list[int], bit_depth: int) -> PhaseLUT:
    """The table read from the signals of the measured levels `kept` (indices) alone."""
    chosen = np.array([grays[k] for k in kept])
    return lut_from_response(chosen, phase_response(chosen, np.array([signals[k] for k in kept])), bit_depth)


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
        new, unjudged = None, None
        if lut is not None:
            try:
                new = round(held_out_misfit(grays, signals, lambda kept: _table(grays, signals, kept, slm.bit_depth)),
                            5)
            except CalibrationError as exc:
                unjudged = str(exc)
        verdict = Verdict("lookup table", channel.name, "held-out signal misfit", new,
                          round(held_out_misfit(grays, signals, lambda kept: old), 5) if complete else None,
                          details={"signal": round(signals[0], 6) if signals else None},
                          replaces="stored one" if channel.name in context.calibration.lut_files()
                          else "profile's table" if channel.name in slm.lut else "linear table")
        if signals:
            verdict.check(signals[0] >= MIN_SIGNAL, f"no light reached the camera: the gray-0 grating's zero order at "
                                                    f"{signals[0]:.2%} of full scale, below {MIN_SIGNAL:.1%}")
        if problem is not None:
            verdict.check(False, f"no table could be read: {problem}")
            return {"grays": grays[:len(signals)], "signals": signals, "problem": problem,
                    "calibration": context.store_calibration(verdict, lambda calibration: None, {})}
        assert lut is not None and phases is not None
        verdict.check(unjudged is None, f"the table cannot be judged on gray levels it was not read from (half of them "
                                        f"give no table: {unjudged}): measure more levels (a smaller gray_step)")
        if new is not None:
            verdict.check(new <= MAX_MISFIT, f"held-out signal misfit {new:.4g} of the span, above the bound "
                                             f"{MAX_MISFIT:g}")
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
