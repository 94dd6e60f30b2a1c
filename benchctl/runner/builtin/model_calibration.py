"""Model calibration: per colour, display phase patterns that focus random sparse points over the ROI and a constant
phase (which shows the beam itself), capture each, register it onto the target plane (the stored registration) and
fit the propagation model's wavefront error (Zernike terms at the SLM), beam (Gaussian waist and offset), SLM
crosstalk and zero order by gradient descent through the differentiable propagation (optics.fitted). The fit is
stored per profile (calibration/<profile>/optical-model.json), where generation, SGD and the simulated scores of
later runs find it (OpticalSetup.field_model).
"""

from __future__ import annotations

import time
from functools import partial
from typing import Annotated, Any

import numpy as np
import torch
from msgspec import Meta

from benchctl.images import read_image
from benchctl.optics.aberration import ZERNIKE_TERMS
from benchctl.optics.fitted import calibration_patterns, fit_optics
from benchctl.profiles import LaserChannel, NonNegativeInt, Positive
from benchctl.runner.api import (
    BenchctlError,
    Calibration,
    Context,
    ExposureParameters,
    RegistrationMode,
    Report,
    Step,
    channels,
    exposure_step,
    line_plot,
    load_exposure,
    power_w,
    registered,
    registered_saturation,
    save_hologram,
    table,
    unknown_setpoints,
)
from benchctl.runner.builtin import registration

MAX_SATURATED = 1e-3  # fraction of ROI pixels clipped in a capture above which the fit is refused
DESCRIPTION = ("random-point and flat phase patterns per colour, captured, registered; wavefront, beam, crosstalk and "
               "zero order fitted and stored")


class ModelCalibrationParameters(ExposureParameters, kw_only=True):
    """The calibration patterns and the fit."""

    # 4 patterns: more move the fitted coefficients by little (docs/model_calibration.md)
    patterns: Annotated[int, Meta(ge=1)] = 4
    spacing_px: Annotated[int, Meta(ge=2)] = 6  # one focused point per spacing^2 ROI pixels
    fit_steps: Annotated[int, Meta(ge=2)] = 120  # Adam steps of the fit (half blurred, half sharp)
    learning_rate: Positive = 0.03
    beam: bool = True  # fit the beam's waist and offset too
    # also show a constant phase: its capture is the beam itself, fitted by gain alone, which pins the waist that
    # the point patterns leave loose (and with it the zero order and crosstalk: docs/model_calibration.md)
    flat: bool = True
    crosstalk: bool = True  # fit the SLM's pixel crosstalk too (a blur of the driven phase)
    # one crosstalk for the panel, the median of the colours' fits: the liquid crystal's fringing is the same in
    # pixels at every wavelength, and one colour's fit can trade it for the camera's blur, which SGD then
    # over-compensates (docs/model_calibration.md)
    panel_crosstalk: bool = True
    zero_order: bool = True  # fit the fraction of the light the panel leaves unmodulated too
    camera_blur: bool = True  # compare through a fitted blur of the captures (camera optics, sampling, registration)
    seed: NonNegativeInt = 0  # of the random points
    registration: RegistrationMode = "auto"


PARAMETERS = ModelCalibrationParameters


def plan(context: Context) -> list[Step]:
    """Registration if needed; per colour: patterns, one exposure per pattern, the fit; the report."""
    unknown_setpoints(context)
    used = channels(context)
    params = context.parameters(ModelCalibrationParameters)
    steps = registration.registration_first(context, used, params, params.registration)
    count = params.patterns + params.flat
    for channel in used:
        steps.append(Step(f"model/patterns/{channel.name}", f"{count} calibration patterns ({channel.name})",
                          _patterns(channel)))
        for k in range(count):
            steps.append(exposure_step(context, f"model/capture/{channel.name}/{k}", channel, power_w(context, channel),
                                       partial(_pattern_frame, channel=channel.name, k=k),
                                       f"expose calibration pattern {k + 1}/{count}"
                                       + (" (flat)" if k == params.patterns else "")))
        steps.append(Step(f"model/fit/{channel.name}", f"fit wavefront, beam, crosstalk and zero order "
                          f"({channel.name})", _fitter(channel)))
    panel = params.crosstalk and params.panel_crosstalk and len(used) > 1
    if panel:
        steps.append(Step("model/panel", "one crosstalk for the panel: the median of the colours' fits",
                          _panel(used)))
    steps.append(Step("report", "metrics.json, metrics.csv and report.html", _reporter(used, panel)))
    return steps


def _patterns(channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        setup = context.setup(channel.name)
        params = context.parameters(ModelCalibrationParameters)
        phases = calibration_patterns(setup.slm_propagator(), setup.roi, params.patterns, seed=params.seed,
                                      spacing_px=params.spacing_px)
        if params.flat:
            phases = torch.cat([phases, torch.zeros_like(phases[:1])])
        files = [save_hologram(context, context.encode(phase, channel.name),
                               f"model-{channel.name}-{'flat' if k == params.patterns else k}.png")
                 for k, phase in enumerate(phases)]
        return {"files": files, "flat": params.flat}

    return action


def _pattern_frame(context: Context, channel: str, k: int) -> np.ndarray:
    return read_image(context.path(context.result(f"model/patterns/{channel}")["files"][k]))


def _fitter(channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        setup = context.setup(channel.name)
        registration_entry = context.calibration.registrations()[channel.name]
        shown, captured, saturated = [], [], 0.0
        for k, file in enumerate(context.result(f"model/patterns/{channel.name}")["files"]):
            shown.append(torch.from_numpy(context.slm.driven(read_image(context.path(file)), channel.name)))
            image, _ = load_exposure(context, f"model/capture/{channel.name}/{k}")
            captured.append(torch.from_numpy(registered(context, image, channel)))
            saturated = max(saturated, registered_saturation(context, image, channel))
        if saturated > MAX_SATURATED:
            raise BenchctlError(f"model calibration {channel.name}: {saturated:.2%} of the ROI is saturated in a "
                                "capture (the fit needs linear images): lower the setpoint or the exposure")
        start = time.perf_counter()
        params = context.parameters(ModelCalibrationParameters)
        flat = bool(context.result(f"model/patterns/{channel.name}").get("flat"))
        fit = fit_optics(setup.target_propagator(), setup.roi, torch.stack(shown), torch.stack(captured),
                         beam=params.beam, crosstalk=params.crosstalk, zero_order=params.zero_order,
                         camera_blur=params.camera_blur,
                         dark_background=[False] * (len(shown) - flat) + [True] * flat, iterations=params.fit_steps,
                         learning_rate=params.learning_rate, progress=context.progress(f"      fit {channel.name}"))
        seconds = time.perf_counter() - start
        entry = {**fit.model.to_dict(), "residual": round(fit.residual, 5),
                 "initial_residual": round(fit.initial_residual, 5), "patterns": len(shown) - flat, "flat": flat,
                 "camera_blur_px": fit.camera_blur_px}
        context.save_calibration(lambda calibration: calibration.save_model(channel.name, entry))
        waves = ", ".join(f"{name} {value:+.3f}" for name, value in fit.model.zernike_waves)
        context.say(f"      {channel.name}: {waves} waves; waist {fit.model.waist_m * 1e3:.2f} mm; crosstalk "
                    f"{fit.model.crosstalk_px:.3f} px; zero order {fit.model.zero_order:.3f}; "
                    f"residual {fit.initial_residual:.3f} -> {fit.residual:.3f} "
                    f"({seconds:.1f} s)")
        through_model = bool(registration_entry.get("through_model"))
        if not through_model:
            context.say(f"      {_registration_note(channel.name)}")
        return {**entry, "seconds": round(seconds, 2), "losses": [round(v, 6) for v in fit.losses],
                "registration_through_model": through_model}

    return action


def _registration_note(colour: str) -> str:
    return (f"{colour}: the registration was made without a fitted model, so it holds any distortion the aberrations "
            "gave its dots: register again (the dots are then displayed through this model), then calibrate again "
            "(docs/model_calibration.md)")


def _panel(used: list[LaserChannel]):
    def action(context: Context) -> dict[str, Any]:
        fitted = {c.name: context.result(f"model/fit/{c.name}")["crosstalk_px"] for c in used}
        shared = round(float(np.median(list(fitted.values()))), 5)
        models = context.calibration.models()

        def store(calibration: Calibration) -> None:
            for name, value in fitted.items():
                entry = {key: item for key, item in models[name].items() if key not in ("geometry", "created")}
                calibration.save_model(name, {**entry, "crosstalk_px": shared, "crosstalk_fitted_px": value})

        context.save_calibration(store)
        context.say(f"      crosstalk {shared:.3f} px for every colour (fitted: "
                    + ", ".join(f"{name} {value:.3f}" for name, value in fitted.items()) + ")")
        return {"crosstalk_px": shared, "fitted_px": fitted}

    return action


def _reporter(used: list[LaserChannel], panel: bool):
    def action(context: Context) -> dict[str, Any]:
        fits = {c.name: context.result(f"model/fit/{c.name}") for c in used}
        if panel:
            shared = context.result("model/panel")["crosstalk_px"]
            fits = {name: {**fit, "crosstalk_px": shared, "crosstalk_fitted_px": fit["crosstalk_px"]}
                    for name, fit in fits.items()}
        notes = [_registration_note(name) for name, fit in fits.items() if not fit.get("registration_through_model")]
        return model_calibration_report(context, fits, list(ZERNIKE_TERMS), notes)

    return action


MODEL_NOTE = ("<p>Wavefront error at the SLM: ANSI/OSA Zernike terms, "
              "RMS-normalised over the disc circumscribing the panel. Residual: RMS misfit of the registered captures "
              "relative to their RMS, after the best gain and offset (gain alone for the flat pattern), with the ideal "
              "model (before) and the fitted one (after). Crosstalk: one value for the panel where several colours "
              "were fitted (the median of their fits: the liquid crystal's fringing is the same in pixels at every "
              "wavelength; the residuals are those of each colour's own fit). Camera blur: the blur of the registered "
              "captures (camera optics, sampling, resampling), fitted so that it is not taken for the bench's; "
              "holograms do not use it. The model is stored per profile and used by generation, SGD and the "
              "simulated scores of later runs.</p>")
"""How to read the fitted-model table (the report says it under the table)."""


def model_calibration_report(context: Context, fits: dict[str, dict[str, Any]], terms: list[str],
                             warnings: list[str]) -> dict[str, Any]:
    """Per colour: fitted Zernike coefficients (waves), beam, crosstalk, zero order, residual before and after; the
    fit's loss curves."""
    rows = [{"colour": name, **{f"{t} (waves)": f["zernike_waves"].get(t) for t in terms},
             "waist mm": round(f["waist_mm"], 4), "offset mm": [round(v, 4) for v in f["offset_mm"]],
             "crosstalk px": f.get("crosstalk_px", 0.0),
             **({"crosstalk px, this colour's fit": f["crosstalk_fitted_px"]} if "crosstalk_fitted_px" in f else {}),
             "zero order": f.get("zero_order", 0.0),
             "camera blur px": f.get("camera_blur_px", 0.0),
             "residual before": f["initial_residual"], "residual after": f["residual"],
             "patterns": f"{f['patterns']}{' + flat' if f.get('flat') else ''}",
             "fit s": f["seconds"],
             "registered through a model": "yes" if f.get("registration_through_model") else "no"}
            for name, f in fits.items()]
    by_quantity = [{"": key, **{row["colour"]: row[key] for row in rows}} for key in rows[0] if key != "colour"]
    curves = {name: (list(range(1, len(f["losses"]) + 1)), f["losses"]) for name, f in fits.items()}
    report = Report("Model calibration")
    report.warn(*warnings)
    report.section("Fitted model", table(by_quantity), MODEL_NOTE)
    report.section("Fit", line_plot(curves, "Adam step", "relative residual (first half blurred)"))
    return report.write(context, {"procedure": "model-calibration", "colours": fits}, rows, list(fits),
                        [f"{r['colour']}: residual {r['residual before']:.3f} -> {r['residual after']:.3f}"
                         for r in rows])
