"""Colour capture, the paper's experiment: per target and per colour present in it, generate that colour's
hologram, expose that colour alone, capture RAW frames and dark frames; then register each colour's CFA plane
onto the target with the stored camera-SLM registration, merge the colours, balance them and score the merged
capture against the target, next to the simulated reconstruction and the generation time per colour.

A scene with depth (`rgbd:...`) among the targets is captured as a focal stack, as procedures/focal_stack.toml
captures it (its planes chosen automatically; the camera focused at each through the focus calibration).

On a profile without them, it first measures the SLM's lookup tables (lut_calibration = "auto") and registers
the camera (registration = "auto"), with the same steps as those procedures; both are then stored for later runs.

With exposure = "auto" (the default) each colour of each target is first probed with one frame at its working
setpoint; the capture then uses the laser power that puts that colour's peak at `peak_goal` of full scale (never
above the channel's max_power_mw), so no colour is lost in read noise or clipped. "fixed" keeps the setpoints.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable, Iterable
from typing import Annotated, Any, Literal

import msgspec
import numpy as np
import torch
from msgspec import Meta

from benchctl.capture.colour_planes import merge_capture
from benchctl.capture.exposure import PEAK_PERCENTILE
from benchctl.cgh import DEFAULT_METHOD, get_method
from benchctl.optics import colour_scores, crop_roi, lsq_scale
from benchctl.optics.metrics import pareto_front
from benchctl.profiles import LaserChannel
from benchctl.runner.api import (
    ERROR_FULL_SCALE,
    BenchctlError,
    Context,
    ExposureCap,
    ExposureMode,
    HologramParameters,
    PeakGoal,
    RegistrationMode,
    Report,
    Step,
    channels,
    check_method,
    error_map,
    exposure_cap_w,
    exposure_step,
    figure,
    front_plot,
    hologram_step,
    load_array,
    load_exposure,
    power_w,
    prepared_target,
    probe_step,
    probed_power,
    registered,
    registered_saturation,
    row,
    save_image,
    shown,
    table,
    target_label,
    target_plane,
    unknown_caps,
    unknown_setpoints,
)
from benchctl.runner.builtin import focal_stack, lut_calibration, registration
from benchctl.scenes import is_scene
from benchctl.targets import active_channels

AUTO_LUT_GRAY_STEP = 16  # every 16th gray level: 17 exposures per colour, errors below 0.01 rad on the simulator
DESCRIPTION = "holograms per colour, each colour exposed alone, RAW capture, registration, merge, scores"


class ColourCaptureParameters(HologramParameters, kw_only=True):
    """What to show, how often, and what to do first when calibration is missing."""

    targets: Annotated[tuple[str, ...], Meta(min_length=1)] = ("chart:bars",)
    # one method, or several: each target is then captured with each, and the report draws their front
    # Wider than HologramParameters.method (str), which a type checker refuses: the plan gives every step a
    # one-method copy (_options), so no step meets a tuple.
    method: str | Annotated[tuple[str, ...], Meta(min_length=1)] = DEFAULT_METHOD  # type: ignore[assignment]
    repeats: Annotated[int, Meta(ge=1, le=1000)] = 1
    registration: RegistrationMode = "auto"
    # "auto": measure the SLM's lookup table first for colours that have none; "skip": use what there is
    lut_calibration: Literal["auto", "skip"] = "auto"
    exposure: ExposureMode = "auto"  # "auto": a probe frame per colour sets the power (peak at peak_goal); "fixed"
    peak_goal: PeakGoal = 0.7  # fraction of full scale
    max_exposure_power: ExposureCap = None  # the most "auto" may set: "5mW", "10%" or per colour; default max_power_mw


PARAMETERS = ColourCaptureParameters


def plan(context: Context) -> list[Step]:
    """Registration if needed, then per target: holograms, exposures (per repeat), processing; the report."""
    params = context.parameters(ColourCaptureParameters)
    unknown_setpoints(context)
    unknown_caps(context, params.max_exposure_power)
    used = channels(context)
    steps: list[Step] = []
    methods = list(dict.fromkeys([params.method] if isinstance(params.method, str) else params.method))
    options = {method: _options(params, method, several=len(methods) > 1) for method in methods}
    if len(methods) > 1 and params.checkpoint and not any(o.checkpoint for o in options.values()):
        raise BenchctlError(f"parameters.checkpoint: none of the methods {methods} is a learned method that takes one")
    for method in methods:
        check_method(context, used, options[method])
    calibrated = {*context.calibration.lut_files(), *(context.profile.slm.lut if context.profile.slm else {})}
    uncalibrated = [c for c in used if c.name not in calibrated]
    if uncalibrated and params.lut_calibration == "auto":
        steps += lut_calibration.lut_steps(context, uncalibrated,
                                           lut_calibration.PARAMETERS(gray_step=AUTO_LUT_GRAY_STEP))
    steps += registration.registration_first(context, used, options[methods[0]], params.registration)
    calibrated_here = [step.key for step in steps if step.key.endswith("/fit") or "/fit/" in step.key]
    labels: set[str] = {registration.LABEL}  # registration's holograms are named after it
    targets, stacks = [], []
    for spec in params.targets:
        if is_scene(spec):  # a scene with depth is captured as a focal stack, as procedures/focal_stack.toml does
            base = focal_stack.scene_label(spec, labels)
            for method in methods:
                label = base if len(methods) == 1 else target_label(f"{base}-{method.replace('+', '-')}", labels)
                scene = focal_stack.stack_scene(context, spec, label, None, False, used, "parameters.targets",
                                                "procedures/focal_stack.toml with planes = {}")
                steps += focal_stack.stack_steps(context, scene, options[method], params.exposure, params.peak_goal,
                                                 params.max_exposure_power)
                stacks.append(label)
            continue
        base, target = target_label(spec, labels), prepared_target(context.profile, spec, "parameters.targets")
        present = active_channels(target)
        lit = [c for c in used if present[target_plane(c)]]
        if not lit:
            raise BenchctlError(f"parameters.targets: {spec!r} has none of the colours {[c.name for c in used]}")
        for method in methods:
            label = base if len(methods) == 1 else target_label(f"{base}-{method.replace('+', '-')}", labels)
            targets.append((spec, label, lit))
            steps += _capture_steps(context, spec, label, lit, target, options[method])
    steps.append(Step("report", "metrics.json, metrics.csv and report.html",
                      _reporter(targets, stacks, used, calibrated_here)))
    return steps


def _options(params: ColourCaptureParameters, method: str, several: bool) -> ColourCaptureParameters:
    """The parameters one of the methods runs with. With several, `iterations` is the budget of the iterative
    ones and `checkpoint` the model of the learned ones; the others use their own defaults."""
    if not several:
        return msgspec.structs.replace(params, method=method)
    try:
        chosen = get_method(method)
    except BenchctlError as exc:
        raise BenchctlError(f"parameters.method: {exc}") from None
    return msgspec.structs.replace(
        params, method=method, iterations=params.iterations if chosen.default_iterations is not None else None,
        checkpoint=params.checkpoint if chosen.network is not None else None)


def _capture_steps(context: Context, spec: str, label: str, lit: list[LaserChannel], target: torch.Tensor,
                   options: ColourCaptureParameters) -> list[Step]:
    """One target with one method (`options.method`): holograms per colour, probes, exposures per repeat,
    processing."""
    steps = [hologram_step(f"hologram/{label}/{c.name}", label, target, c, options) for c in lit]
    powers: dict[str, float | Callable[[Context], float]] = {c.name: power_w(context, c) for c in lit}
    caps = {c.name: exposure_cap_w(context, c, options.max_exposure_power) for c in lit}
    if options.exposure == "auto":
        for channel in lit:
            key = f"probe/{label}/{channel.name}"
            steps.append(probe_step(context, key, channel, shown(f"hologram/{label}/{channel.name}"),
                                    f"probe exposure {label}", options.peak_goal, caps[channel.name]))
            powers[channel.name] = probed_power(key)
    for repeat in _repeats(options.repeats):
        for channel in lit:
            steps.append(exposure_step(context, f"capture/{label}{repeat}/{channel.name}", channel,
                                       powers[channel.name], shown(f"hologram/{label}/{channel.name}"),
                                       f"expose {label}{repeat}", max_w=caps[channel.name]))
        steps.append(Step(f"process/{label}{repeat}", f"register, merge and score {label}{repeat}",
                          _processor(spec, label, repeat, lit, target, str(options.method))))
    return steps


def _repeats(count: int) -> list[str]:
    return [""] if count == 1 else [f"-r{n}" for n in range(1, count + 1)]


def _processor(spec: str, label: str, repeat: str, lit: list[LaserChannel], target: torch.Tensor, method: str):
    def action(context: Context) -> dict[str, Any]:
        assert context.profile.optics is not None
        target_roi = crop_roi(target, context.profile.optics.roi)
        planes, saturation, simulated = {}, {}, torch.zeros_like(target_roi)
        for channel in lit:
            index = target_plane(channel)
            image, _ = load_exposure(context, f"capture/{label}{repeat}/{channel.name}")
            planes[index] = registered(context, image, channel)
            saturation[index] = registered_saturation(context, image, channel)
            sim = load_array(context, context.result(f"hologram/{label}/{channel.name}")["simulated"])
            simulated[index] = torch.from_numpy(sim).square().clamp(0, 1)
        capture = merge_capture(planes, target_roi, saturation=saturation)
        folder = label + repeat
        target_linear = target_roi.square()
        scaled = lsq_scale(simulated, target_linear) * simulated  # as the simulated scores compare it
        files = {
            "target": save_image(context, target_linear, folder, "target.png", srgb=True),
            "capture": save_image(context, capture.merged.linear, folder, "capture.png", srgb=True),
            "capture_linear": save_image(context, capture.merged.linear, folder, "capture-linear.png"),
            "simulated": save_image(context, simulated, folder, "simulated.png", srgb=True),
            "error_capture": save_image(context, error_map(capture.merged.linear, target_linear), folder,
                                        "error-capture.png"),
            "error_simulated": save_image(context, error_map(scaled, target_linear), folder, "error-simulated.png"),
        }
        names = {target_plane(c): c.name for c in lit}
        for index, plane in planes.items():
            peak = float(max(plane.max(), 1e-12))
            files[f"plane_{names[index]}"] = save_image(context, np.clip(plane, 0, None) / peak, folder,
                                                        f"plane-{names[index]}.png")
        per_colour = {}
        for channel in lit:
            index = target_plane(channel)
            generated = context.result(f"hologram/{label}/{channel.name}")
            per_colour[channel.name] = {
                "capture": {k: round(v, 4) for k, v in capture.scores[index].items()},
                "simulated": generated["scores"], "generation_s": generated["seconds"],
                "cached": generated["cached"], "gain": capture.merged.gains[index],
                "saturated_fraction": saturation[index],
                "power_w": context.result(f"capture/{label}{repeat}/{channel.name}")["setpoint_w"],
                "peak": round(float(np.percentile(planes[index], PEAK_PERCENTILE)), 4),
            }
            if context.parameters(ColourCaptureParameters).exposure == "auto":
                choice = context.result(f"probe/{label}/{channel.name}")["auto_exposure"]
                per_colour[channel.name].update(goal=choice["goal"], limited_by_max=choice["limited_by_max"])
        return {
            "target": spec, "method": method, "label": label + repeat, "files": files,
            "colours": per_colour, "warnings": list(capture.warnings),
            "merged": {"capture": {k: round(v, 4) for k, v in capture.merged_scores.items()},
                       "simulated": {k: round(v, 4) for k, v in colour_scores(simulated, target_roi).items()}},
        }

    return action


def _reporter(targets: list[tuple[str, str, list[LaserChannel]]], stacks: list[str], used: list[LaserChannel],
              calibrated_here: list[str]):
    def action(context: Context) -> dict[str, Any]:
        results = [context.result(f"process/{label}{repeat}")
                   for _, label, _ in targets
                   for repeat in _repeats(context.parameters(ColourCaptureParameters).repeats)]
        fits = {key: context.result(key) for key in calibrated_here}
        return colour_capture_report(context, results, [c.name for c in used], fits,
                                     [context.result(f"stack/{label}") for label in stacks])

    return action


def _flat(prefix: str, scores: dict[str, Any]) -> dict[str, Any]:
    return {f"{prefix}{key}": value for key, value in scores.items()}


SHORT_OF_GOAL = 0.8  # a colour whose capture peaks below this fraction of its exposure goal is said in the report


def exposure_warnings(label: str, colours: dict[str, dict[str, Any]]) -> list[str]:
    """Colours whose capture peaked well short of their automatic-exposure goal (the laser at its limit, or the
    probe misled), said with the numbers: the report's "No warnings." must be true."""
    lines = []
    for name, colour in colours.items():
        goal = colour.get("goal")
        if goal and colour["peak"] < SHORT_OF_GOAL * goal:
            why = (f" (the laser at its max_power_mw, {colour['power_w'] * 1e3:.3g} mW)" if colour["limited_by_max"]
                   else "")
            lines.append(f"{label}: {name} peaked at {colour['peak']:.0%} of full scale, short of its {goal:.0%} "
                         f"exposure goal{why}: a noisier capture than planned")
    return lines


def colour_capture_report(context: Context, results: list[dict[str, Any]], colours: list[str],
                          fits: dict[str, dict[str, Any]] | None = None,
                          stacks: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """Per target: target, simulation and capture side by side, each colour's capture, error maps, per-colour and
    merged scores; per scene with depth its focal stack (`stacks`: the focal-stack summaries); the lookup tables and
    registration this run measured first (`fits`, by step key); across methods the speed against error;
    metrics.json and metrics.csv (one row per target and colour, plus the merged row)."""
    stacks = stacks or []
    report = Report(f"Colour capture: {', '.join([*(r['label'] for r in results), *(s['label'] for s in stacks)])}")
    rows = []
    for result in results:
        label = result["label"]
        for name, colour in result["colours"].items():
            rows.append({"target": result["target"], "label": label, "colour": name,
                         "generation_s": colour["generation_s"], "cached": colour["cached"], "gain": colour["gain"],
                         "saturated_fraction": colour["saturated_fraction"], "power_w": colour["power_w"],
                         "peak": colour["peak"],
                         **_flat("simulated_", colour["simulated"]), **_flat("capture_", colour["capture"])})
        rows.append({"target": result["target"], "label": label, "colour": "merged",
                     **_flat("simulated_", result["merged"]["simulated"]),
                     **_flat("capture_", result["merged"]["capture"])})
        report.warn(*[f"{label}: {w}" for w in result["warnings"]], *exposure_warnings(label, result["colours"]))
        files = result["files"]
        pictures = [figure(context, files[key], caption) for key, caption in (
            ("target", "target (sRGB)"), ("simulated", "simulated reconstruction"), ("capture", "merged capture"))]
        planes = [figure(context, files[f"plane_{name}"], f"{name} captured (registered, its own scale)")
                  for name in result["colours"]]
        errors = [figure(context, files[key], caption) for key, caption in (
            ("error_simulated", "simulation: error against the target"),
            ("error_capture", "capture: error against the target")) if key in files]
        score_rows = [{"colour": name, "generation s": c["generation_s"],
                       "simulated PSNR dB (amplitude)": c["simulated"]["psnr_amplitude_db"],
                       "capture PSNR dB (amplitude)": c["capture"]["psnr_amplitude_db"],
                       "simulated SSIM (sRGB)": c["simulated"]["ssim_srgb"],
                       "capture SSIM (sRGB)": c["capture"]["ssim_srgb"], "gain": c["gain"],
                       "laser mW": c["power_w"] * 1e3, "peak": c["peak"], "saturated": c["saturated_fraction"]}
                      for name, c in result["colours"].items()]
        merged = result["merged"]
        merged_rows = [{"image": kind, "PSNR dB linear": s["psnr_linear_db"], "PSNR dB sRGB": s["psnr_srgb_db"],
                        "SSIM sRGB": s["ssim_srgb"]} for kind, s in merged.items()]
        note = (f"<p>Error maps: per pixel the RMS over colours of the sRGB difference from the target, black 0, "
                f"yellow {ERROR_FULL_SCALE:g} or more.</p>" if errors else "")
        report.section(f"Target {result['target']} ({label})", row(*pictures), row(*planes, columns=3),
                       row(*errors, columns=3), note)
        report.section("Per colour (ROI, least-squares scaled)", table(score_rows),
                       "<p>Generation time: the time it took to compute the hologram (for a cached hologram, when it "
                       "was computed). Peak: the capture's brightest 0.1 % as a fraction of full scale.</p>", level=3)
        report.section("Merged colour image", table(merged_rows), level=3)
    for summary in stacks:
        rows += focal_stack.focal_stack_sections(report, context, summary)
    method = context.parameters(HologramParameters).method
    front = method_front(results)
    if len(front) > 1:
        points = [(r["method"], r["seconds per frame"], r["capture PSNR dB sRGB"], r["on front"]) for r in front]
        report.section("Speed against error across methods",
                       front_plot(points, "seconds per frame (every colour)", "merged capture PSNR dB (sRGB)"),
                       table(front), "<p>Per method, means over the targets: the time to compute one frame of every "
                       "colour in the target, and the merged capture's PSNR. Filled markers are on the Pareto front: "
                       "no other method is both at least as fast and at least as good.</p>")
    fits = fits or {}
    luts = {key.split("/")[1]: fit for key, fit in fits.items() if key.startswith("lut/")}
    registrations = {key.split("/")[-1]: fit for key, fit in fits.items() if key.startswith("registration/")}
    if luts:
        lut_calibration.lut_sections(report, luts)
    if registrations:
        registration.registration_sections(report, context, registrations)
    headline = [f"{r['label']}: merged capture PSNR {r['merged']['capture']['psnr_srgb_db']:.2f} dB sRGB, SSIM "
                f"{r['merged']['capture']['ssim_srgb']:.3f} (simulated {r['merged']['simulated']['psnr_srgb_db']:.2f} "
                f"dB, {r['merged']['simulated']['ssim_srgb']:.3f}); generation "
                + ", ".join(f"{n} {c['generation_s']:.2f} s" for n, c in r["colours"].items()) for r in results]
    headline += [focal_stack.stack_headline(summary) for summary in stacks]
    return report.write(context, {"procedure": "colour-capture", "method": method, "targets": results,
                                  "scenes": stacks, "front": front}, rows, colours, headline)


def method_front(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per hologram method of a colour capture: mean seconds per frame (all colours of a target), mean
    merged PSNR / SSIM captured and simulated, and whether it is on the Pareto front of time against captured
    PSNR."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for result in results:
        groups.setdefault(result["method"], []).append(result)
    rows: list[dict[str, Any]] = []
    for method, group in groups.items():
        rows.append({
            "method": method, "targets": len(group),
            "seconds per frame": _mean(sum(c["generation_s"] for c in r["colours"].values()) for r in group),
            "capture PSNR dB sRGB": _mean(r["merged"]["capture"]["psnr_srgb_db"] for r in group),
            "capture SSIM sRGB": _mean(r["merged"]["capture"]["ssim_srgb"] for r in group),
            "simulated PSNR dB sRGB": _mean(r["merged"]["simulated"]["psnr_srgb_db"] for r in group),
        })
    on_front = pareto_front([(r["seconds per frame"], r["capture PSNR dB sRGB"]) for r in rows])
    return [row | {"on front": flag} for row, flag in zip(rows, on_front)]


def _mean(values: Iterable[float]) -> float:
    return round(statistics.fmean(values), 4)
