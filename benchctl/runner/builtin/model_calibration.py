"""Model calibration: per colour, display phase patterns that focus random sparse points over the ROI and a constant
phase (which shows the beam itself), capture each, register it onto the target plane (the stored registration) and
fit the propagation model's wavefront error (Zernike terms at the SLM), beam (Gaussian waist and offset), SLM
crosstalk and zero order by gradient descent through the differentiable propagation (optics.fitted). The fit is
stored per profile (calibration/<profile>/optical-model.json), where generation, SGD and the simulated scores of
later runs find it (OpticalSetup.field_model), if it passes its acceptance test (calibration.acceptance): light reached
the camera, every pattern focused points (a pattern without any holds no information on the wavefront), no capture
clipped, the fit converged and brought its residual to at most MIN_IMPROVEMENT of the ideal model's, and on captures
it was not fitted to (`held_out` further point patterns) its residual is at most MIN_IMPROVEMENT of the ideal
model's, below MAX_RESIDUAL and not above the stored model's.

With `focus_depths_mm` each pattern is captured with the camera focused at each of those depths (from
optics.distance_mm, through the focus calibration), and the model is fitted to all of them at once: its intensity at
each plane against the capture focused there (one gain per pattern for its planes), and judged on the held-out
patterns at all those planes. Captures are ordered by depth, so the focus moves once per depth and colour.
"""

from __future__ import annotations

import math
import time
from functools import partial
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import torch
from msgspec import Meta

from benchctl.capture.exposure import PEAK_PERCENTILE
from benchctl.files import write_json
from benchctl.optics.aberration import ZERNIKE_TERMS
from benchctl.optics.fitted import FitDiverged, FittedOptics, calibration_patterns, fit_optics, model_residual
from benchctl.profiles import LaserChannel, NonNegativeInt
from benchctl.runner.api import (
    BenchctlError,
    Calibration,
    Context,
    ExposureParameters,
    RegistrationMode,
    Report,
    Step,
    Verdict,
    channels,
    exposure_step,
    line_plot,
    load_exposure,
    load_image,
    power_w,
    registered,
    registered_saturation,
    save_hologram,
    table,
    unknown_setpoints,
)
from benchctl.runner.builtin import registration

MAX_SATURATED = 1e-3  # fraction of ROI pixels clipped in a capture above which the fit is not stored
# Acceptance (calibration.acceptance). Light reached the camera: every registered capture's brightest 0.1 % reaches this
# fraction of full scale (a capture without light reads its noise, about 0.05 % on the simulated camera).
MIN_SIGNAL = 0.003
MIN_IMPROVEMENT = 0.9  # the fit brings the residual to at most this fraction of the ideal model's
MAX_RESIDUAL = 0.5  # and below this (fits of working benches: 0.03-0.4, docs/model_calibration.md)
# Fewer points than this per pattern (the ROI's pixels / spacing_px^2, on average) leave the wavefront unmeasured: a
# fit to patterns without points moved the defocus to -0.19 waves where the truth is +0.30, and was stored.
MIN_POINTS = 20
HELD_OUT_SEED = 1_000_003  # the held-out patterns' seed, from `seed`: other points than any fitted pattern's
DESCRIPTION = ("random-point and flat phase patterns per colour, captured, registered; wavefront, beam, crosstalk and "
               "zero order fitted and stored")


class ModelCalibrationParameters(ExposureParameters, kw_only=True):
    """The calibration patterns and the fit."""

    # 4 patterns: more move the fitted coefficients by little (docs/model_calibration.md)
    patterns: Annotated[int, Meta(ge=1)] = 4
    # further point patterns, captured but not fitted: acceptance judges the fit on them (a model that explains only
    # the captures it was fitted to is not stored)
    held_out: Annotated[int, Meta(ge=1, le=16)] = 1
    spacing_px: Annotated[int, Meta(ge=2)] = 6  # one focused point per spacing^2 ROI pixels
    fit_steps: Annotated[int, Meta(ge=2)] = 120  # Adam steps of the fit (half blurred, half sharp)
    # Adam moves each parameter by about this per step (in waves, pupil radii, units of crosstalk and zero order):
    # above 1 one step crosses every realistic value; a fit that diverges below it is not stored
    learning_rate: Annotated[float, Meta(gt=0, le=1)] = 0.03
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
    # capture every pattern focused at each of these depths from optics.distance_mm (the focus calibration puts the
    # camera there) and fit the model at all of them; empty: at the target plane only
    focus_depths_mm: tuple[float, ...] = ()


PARAMETERS = ModelCalibrationParameters


def plan(context: Context) -> list[Step]:
    """Registration if needed; per colour: patterns, one exposure per pattern, the fit; the report."""
    unknown_setpoints(context)
    used = channels(context)
    params = context.parameters(ModelCalibrationParameters)
    _check_points(context, params)
    depths = focus_depths(context)
    steps: list[Step] = []  # planned before registration, so that a missing focus calibration is said first
    count = params.patterns + params.held_out + params.flat
    for channel in used:
        steps.append(Step(f"model/patterns/{channel.name}", f"{count} calibration patterns ({channel.name})",
                          _patterns(channel)))
        for j, depth in enumerate(depths or [None]):
            at = "" if depth is None else f" focused at {depth * 1e3:.2f} mm"
            for k in range(count):
                kind = " (flat)" if k == params.patterns + params.held_out else (
                    " (held out)" if k >= params.patterns else "")
                steps.append(exposure_step(
                    context, _capture_key(channel.name, k, None if depth is None else j), channel,
                    power_w(context, channel), partial(_pattern_frame, channel=channel.name, k=k),
                    f"expose calibration pattern {k + 1}/{count}{kind}{at}", depth_m=depth))
        steps.append(Step(f"model/fit/{channel.name}", f"fit wavefront, beam, crosstalk and zero order "
                          f"({channel.name})", _fitter(channel)))
    steps = registration.registration_first(context, used, params, params.registration) + steps
    panel = params.crosstalk and params.panel_crosstalk and len(used) > 1
    if panel:
        steps.append(Step("model/panel", "one crosstalk for the panel: the median of the colours' fits",
                          _panel(used)))
    steps.append(Step("report", "metrics.json, metrics.csv and report.html", _reporter(used, panel)))
    return steps


def focus_depths(context: Context) -> list[float]:
    """The depths (metres from the SLM) every pattern is captured at: `focus_depths_mm` from the profile's distance,
    distinct and in front of the SLM; none: the target plane, where the camera is."""
    params = context.parameters(ModelCalibrationParameters)
    offsets = params.focus_depths_mm
    if len(set(offsets)) != len(offsets):
        raise BenchctlError(f"parameters.focus_depths_mm: {list(offsets)} names a depth twice")
    depths = [(context.profile.section("optics").distance_mm + offset) * 1e-3 for offset in sorted(offsets)]
    if depths and min(depths) <= 0:
        raise BenchctlError(f"parameters.focus_depths_mm: {min(offsets):g} mm puts a depth behind the SLM")
    return depths


def _capture_key(colour: str, k: int, j: int | None) -> str:
    """Pattern k's capture (at the `j`-th focus depth, where there are several)."""
    return f"model/capture/{colour}/{k}" + ("" if j is None else f"/z{j}")
def _check_points(context: Context, params: ModelCalibrationParameters) -> None:
    """Refuse a spacing that leaves the patterns (nearly) without points, before anything runs."""
    optics = context.profile.require("optics").optics
    assert optics is not None
    rows, cols = optics.roi
    points = rows * cols / params.spacing_px**2
    if points < MIN_POINTS:
        largest = math.isqrt(rows * cols // MIN_POINTS)
        raise BenchctlError(f"parameters.spacing_px: {params.spacing_px} leaves about {points:.3g} point(s) per "
                            f"pattern on the {rows} x {cols} ROI, too few to measure the wavefront (at least "
                            f"{MIN_POINTS}): at most {largest}")


def _patterns(channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        setup = context.setup(channel.name)
        params = context.parameters(ModelCalibrationParameters)
        points = params.patterns + params.held_out
        phases = torch.cat([calibration_patterns(setup.slm_propagator(), setup.roi, count, seed=seed,
                                                 spacing_px=params.spacing_px)
                            for count, seed in ((params.patterns, params.seed),
                                                (params.held_out, params.seed + HELD_OUT_SEED))])
        empty = [k for k, phase in enumerate(phases) if float(phase.max() - phase.min()) == 0]  # no point landed
        if params.flat:
            phases = torch.cat([phases, torch.zeros_like(phases[:1])])
        files = [save_hologram(context, context.encode(phase, channel.name),
                               f"model-{channel.name}-{'flat' if k == points else k}.png")
                 for k, phase in enumerate(phases)]
        return {"files": files, "flat": params.flat, "held_out": params.held_out, "empty": empty}

    return action


def _pattern_frame(context: Context, channel: str, k: int) -> np.ndarray:
    return load_image(context, context.result(f"model/patterns/{channel}")["files"][k])


def _fitter(channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        setup = context.setup(channel.name)
        registration_entry = context.calibration.registrations()[channel.name]
        depths = focus_depths(context)
        made = context.result(f"model/patterns/{channel.name}")
        shown, captured, saturated = [], [], 0.0
        for k, file in enumerate(made["files"]):
            shown.append(torch.from_numpy(context.slm.driven(load_image(context, file), channel.name)))
            planes = []
            for j in range(len(depths)) if depths else [None]:
                image, _ = load_exposure(context, _capture_key(channel.name, k, j))
                planes.append(torch.from_numpy(registered(context, image, channel)))
                saturated = max(saturated, registered_saturation(context, image, channel))
            captured.append(torch.stack(planes) if depths else planes[0])
        # at several depths, the model's intensity at each against the capture focused there
        propagator = setup.planes_propagator(depths) if depths else setup.target_propagator()
        start = time.perf_counter()
        params = context.parameters(ModelCalibrationParameters)
        flat, held = bool(made.get("flat")), int(made.get("held_out", 0))
        fitted = list(range(len(shown) - flat - held)) + list(range(len(shown) - flat, len(shown)))
        held_out = list(range(len(shown) - flat - held, len(shown) - flat))
        dark = [False] * (len(fitted) - flat) + [True] * flat
        phases, images = torch.stack([shown[k] for k in fitted]), torch.stack([captured[k] for k in fitted])
        try:
            fit = fit_optics(propagator, setup.roi, phases, images, beam=params.beam,
                             crosstalk=params.crosstalk, zero_order=params.zero_order,
                             camera_blur=params.camera_blur, dark_background=dark, iterations=params.fit_steps,
                             learning_rate=params.learning_rate, progress=context.progress(f"      fit {channel.name}"))
        except FitDiverged as exc:
            fit, diverged = None, exc
        seconds = time.perf_counter() - start
        old = context.calibration.models().get(channel.name)
        blur = 0.0 if fit is None else fit.camera_blur_px

        def residual_held_out(model: FittedOptics, camera_blur_px: float) -> float | None:
            """`model`'s residual on the held-out captures, which no fit saw (None without any)."""
            if not held_out:
                return None
            return round(model_residual(propagator, setup.roi, torch.stack([shown[k] for k in held_out]),
                                        torch.stack([captured[k] for k in held_out]), model,
                                        camera_blur_px=camera_blur_px), 5)

        ideal = residual_held_out(FittedOptics(), blur)  # seen through the same camera blur: only the optics differ
        before = ideal if old is None else residual_held_out(FittedOptics.from_dict(old),
                                                             float(old.get("camera_blur_px", 0.0)))
        new = None if fit is None else residual_held_out(fit.model, blur)
        signal = min(float(np.percentile(plane.numpy(), PEAK_PERCENTILE)) for image in captured
                     for plane in (image if depths else [image]))
        verdict = Verdict("optical model", channel.name, "held-out residual", new, before,
                          replaces="ideal model" if old is None else "stored one",
                          details={"signal": round(signal, 6), "saturated_fraction": round(saturated, 6),
                                   "held_out": len(held_out), "ideal_held_out_residual": ideal,
                                   "fit_residual": None if fit is None else round(fit.residual, 5),
                                   "stored_fit_residual": None if old is None else old.get("residual")})
        verdict.check(signal >= MIN_SIGNAL, f"no light reached the camera: the brightest 0.1 % of a capture at "
                                            f"{signal:.2%} of full scale, below {MIN_SIGNAL:.1%}")
        empty = made.get("empty", [])
        verdict.check(not empty, f"no information: calibration pattern(s) {', '.join(str(k + 1) for k in empty)} "
                                 f"focus no point (spacing_px {params.spacing_px})")
        verdict.check(bool(held_out), "no held-out capture to judge the fit on (a run made before held_out existed)")
        verdict.check(saturated <= MAX_SATURATED, f"{saturated:.2%} of the ROI saturated in a capture (the fit needs "
                                                  "linear images): lower the setpoint or the exposure")
        if fit is None:
            verdict.check(False, f"{diverged} with learning_rate {params.learning_rate:g}: lower it")
            record = context.store_calibration(verdict, lambda calibration: None, {})
            return {"diverged": str(diverged), "losses": [round(v, 6) for v in diverged.losses],
                    "seconds": round(seconds, 2), "calibration": record}
        verdict.check(fit.residual <= MIN_IMPROVEMENT * fit.initial_residual,
                      f"the fit did not improve on the ideal model: residual {fit.initial_residual:.3f} -> "
                      f"{fit.residual:.3f}, needs at most {MIN_IMPROVEMENT:g} x the start")
        if new is not None and ideal is not None:
            verdict.check(new <= MIN_IMPROVEMENT * ideal,
                          f"on the held-out capture(s) the fit explains no more than the ideal model: residual "
                          f"{new:.3f} against the ideal model's {ideal:.3f}, needs at most {MIN_IMPROVEMENT:g} x it")
            verdict.check(new <= MAX_RESIDUAL, f"held-out residual {new:.3f} above the bound {MAX_RESIDUAL:g}")
        verdict.no_worse()
        entry = {**fit.model.to_dict(), "residual": round(fit.residual, 5),
                 "initial_residual": round(fit.initial_residual, 5), "held_out_residual": new,
                 "patterns": len(fitted) - flat, "held_out": len(held_out), "flat": flat,
                 "camera_blur_px": fit.camera_blur_px, "focus_depths_mm": [round(z * 1e3, 6) for z in depths]}
        waves = ", ".join(f"{name} {value:+.3f}" for name, value in fit.model.zernike_waves)
        context.say(f"      {channel.name}: {waves} waves; waist {fit.model.waist_m * 1e3:.2f} mm; crosstalk "
                    f"{fit.model.crosstalk_px:.3f} px; zero order {fit.model.zero_order:.3f}; "
                    f"residual {fit.initial_residual:.3f} -> {fit.residual:.3f} "
                    f"({seconds:.1f} s)")

        def candidate(path: Path) -> None:
            write_json(path, {"profile": context.profile.name, "colour": channel.name, "model": entry,
                              "acceptance": verdict.record(False, [])})

        record = context.store_calibration(verdict, lambda calibration: calibration.save_model(channel.name, entry),
                                           {f"optical-model-{channel.name}.json": candidate})
        through_model = bool(registration_entry.get("through_model"))
        if not through_model:
            context.say(f"      {_registration_note(channel.name)}")
        return {**entry, "seconds": round(seconds, 2), "losses": [round(v, 6) for v in fit.losses],
                "registration_through_model": through_model, "calibration": record}

    return action


def _registration_note(colour: str) -> str:
    return (f"{colour}: the registration was made without a fitted model, so it holds any distortion the aberrations "
            "gave its dots: register again (the dots are then displayed through this model), then calibrate again "
            "(docs/model_calibration.md)")


def _panel(used: list[LaserChannel]):
    def action(context: Context) -> dict[str, Any]:
        results = {c.name: context.result(f"model/fit/{c.name}") for c in used}
        fitted = {name: result["crosstalk_px"] for name, result in results.items() if result["calibration"]["stored"]}
        if len(fitted) < 2:
            context.say(f"      one crosstalk for the panel needs two stored fits; {len(fitted)} stored: each keeps "
                        "its own")
            return {"skipped": f"{len(fitted)} fit(s) stored", "fitted_px": fitted}
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
        shared = context.result("model/panel").get("crosstalk_px") if panel else None
        if shared is not None:
            fits = {name: {**fit, "crosstalk_px": shared, "crosstalk_fitted_px": fit["crosstalk_px"]}
                    if fit["calibration"]["stored"] else fit for name, fit in fits.items()}
        notes = [_registration_note(name) for name, fit in fits.items()
                 if "zernike_waves" in fit and not fit.get("registration_through_model")]
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
    """Per colour: fitted Zernike coefficients (waves), beam, crosstalk, zero order, residual before and after; whether
    each model was stored (its residual beside the stored model's on the same captures); the fit's loss curves."""
    rows = [{"colour": name, **{f"{t} (waves)": f["zernike_waves"].get(t) for t in terms},
             "waist mm": round(f["waist_mm"], 4), "offset mm": [round(v, 4) for v in f["offset_mm"]],
             "crosstalk px": f.get("crosstalk_px", 0.0),
             **({"crosstalk px, this colour's fit": f["crosstalk_fitted_px"]} if "crosstalk_fitted_px" in f else {}),
             "zero order": f.get("zero_order", 0.0),
             "camera blur px": f.get("camera_blur_px", 0.0),
             "residual before": f["initial_residual"], "residual after": f["residual"],
             "held-out residual": f.get("held_out_residual"),
             "patterns": f"{f['patterns']}{' + flat' if f.get('flat') else ''}",
             "captured at mm": f.get("focus_depths_mm") or "the target plane",
             "fit s": f["seconds"],
             "registered through a model": "yes" if f.get("registration_through_model") else "no",
             "stored": "yes" if f["calibration"]["stored"] else "no"}
            for name, f in fits.items() if "zernike_waves" in f]
    curves = {name: (list(range(1, len(f["losses"]) + 1)), f["losses"]) for name, f in fits.items()}
    report = Report("Model calibration")
    report.warn(*warnings)
    report.calibrations([f["calibration"] for f in fits.values()])
    if rows:
        by_quantity = [{"": key, **{row["colour"]: row.get(key) for row in rows}} for key in rows[0] if key != "colour"]
        report.section("Fitted model", table(by_quantity), MODEL_NOTE)
    report.section("Fit", line_plot(curves, "Adam step", "relative residual (first half blurred)"))
    headline = [f"{name}: " + (f"residual {f['initial_residual']:.3f} -> {f['residual']:.3f}" if "residual" in f
                               else f"the fit diverged ({f['diverged']})")
                + ("" if f["calibration"]["stored"] else "; NOT stored") for name, f in fits.items()]
    return report.write(context, {"procedure": "model-calibration", "colours": fits}, rows, list(fits), headline)
