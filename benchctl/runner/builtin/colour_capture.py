"""Colour capture, the paper's experiment: per target and per colour present in it, generate that colour's
hologram, expose that colour alone, capture RAW frames and dark frames; then register each colour's CFA plane
onto the target with the stored camera-SLM registration, merge the colours, balance them and score the merged
capture against the target, next to the simulated reconstruction and the generation time per colour.

On a profile without them, it first measures the SLM's lookup tables (lut_calibration = "auto") and registers
the camera (registration = "auto"), with the same steps as those procedures; both are then stored for later runs.

With exposure = "auto" (the default) each colour of each target is first probed with one frame at its working
setpoint; the capture then uses the laser power that puts that colour's peak at `peak_goal` of full scale (never
above the channel's max_power_mw), so no colour is lost in read noise or clipped. "fixed" keeps the setpoints.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import msgspec
import numpy as np
import torch
from msgspec import Meta

from benchctl.cgh.method import get_method
from benchctl.capture.colour_planes import PEAK_PERCENTILE, merge_capture, registered_plane, roi_saturation
from benchctl.errors import BenchctlError
from benchctl.optics import colour_scores, crop_roi
from benchctl.profiles import LaserChannel
from benchctl.runner.builtin import lut_calibration, registration
from benchctl.runner.auto_exposure import Exposure, PeakGoal, probe_step, probed_power
from benchctl.runner.procedure import Context, Step
from benchctl.runner.report import colour_capture_report
from benchctl.runner.holograms import target_plane
from benchctl.runner.steps import (
    HologramParameters,
    Registration,
    channels,
    check_method,
    displayed_frame,
    exposure_step,
    hologram_step,
    load_exposure,
    power_w,
    prepared_target,
    target_label,
    unknown_setpoints,
    write_linear16,
)
from benchctl.targets import active_channels

AUTO_LUT_GRAY_STEP = 16  # every 16th gray level: 17 exposures per colour, errors below 0.01 rad on the simulator
DESCRIPTION = "holograms per colour, each colour exposed alone, RAW capture, registration, merge, scores"


class ColourCaptureParameters(HologramParameters, kw_only=True):
    """What to show, how often, and what to do first when calibration is missing."""

    targets: Annotated[tuple[str, ...], Meta(min_length=1)] = ("chart:bars",)
    # one method, or several: each target is then captured with each, and the report draws their front
    method: str | Annotated[tuple[str, ...], Meta(min_length=1)] = "dpac"
    repeats: Annotated[int, Meta(ge=1, le=1000)] = 1
    registration: Registration = "auto"
    # "auto": measure the SLM's lookup table first for colours that have none; "skip": use what there is
    lut_calibration: Literal["auto", "skip"] = "auto"
    exposure: Exposure = "auto"  # "auto": a probe frame per colour sets the power (peak at peak_goal); "fixed"
    peak_goal: PeakGoal = 0.7  # fraction of full scale


PARAMETERS = ColourCaptureParameters


def plan(context: Context) -> list[Step]:
    """Registration if needed, then per target: holograms, exposures (per repeat), processing; the report."""
    params = context.parameters(ColourCaptureParameters)
    unknown_setpoints(context)
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
    labels: set[str] = set()
    targets = []
    for spec in params.targets:
        base, target = target_label(spec, labels), prepared_target(context.profile, spec)
        present = active_channels(target)
        lit = [c for c in used if present[target_plane(c)]]
        if not lit:
            raise BenchctlError(f"parameters.targets: {spec!r} has none of the colours {[c.name for c in used]}")
        for method in methods:
            label = base if len(methods) == 1 else target_label(f"{base}-{method.replace('+', '-')}", labels)
            targets.append((spec, label, lit))
            steps += _capture_steps(context, spec, label, lit, target, options[method])
    steps.append(Step("report", "metrics.json, metrics.csv and report.html", _reporter(targets, used)))
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
    powers = {c.name: power_w(context, c) for c in lit}
    if options.exposure == "auto":
        for channel in lit:
            key = f"probe/{label}/{channel.name}"
            steps.append(probe_step(context, key, (label, "probe", channel.name), channel,
                                    _shown(f"hologram/{label}/{channel.name}"), f"probe exposure {label}",
                                    options.peak_goal))
            powers[channel.name] = probed_power(key)
    for repeat in _repeats(options.repeats):
        for channel in lit:
            steps.append(exposure_step(
                context, f"capture/{label}{repeat}/{channel.name}", (label + repeat, channel.name), channel,
                powers[channel.name], _shown(f"hologram/{label}/{channel.name}"), f"expose {label}{repeat}"))
        steps.append(Step(f"process/{label}{repeat}", f"register, merge and score {label}{repeat}",
                          _processor(spec, label, repeat, lit, target, str(options.method))))
    return steps


def _repeats(count: int) -> list[str]:
    return [""] if count == 1 else [f"-r{n}" for n in range(1, count + 1)]


def _shown(hologram_key: str):
    return lambda context: displayed_frame(context, hologram_key)


def _processor(spec: str, label: str, repeat: str, lit: list[LaserChannel], target: torch.Tensor, method: str):
    def action(context: Context) -> dict[str, Any]:
        profile = context.profile
        assert profile.slm is not None and profile.optics is not None
        shape, roi = profile.slm.shape, profile.optics.roi
        homographies = context.calibration.registrations()
        target_roi = crop_roi(target, roi)
        planes, saturation, simulated = {}, {}, torch.zeros_like(target_roi)
        for channel in lit:
            index = target_plane(channel)
            image, _ = load_exposure(context, f"capture/{label}{repeat}/{channel.name}")
            homography = np.asarray(homographies[channel.name]["homography"], dtype=np.float64)
            planes[index] = registered_plane(image, index, homography, shape, roi)
            saturation[index] = roi_saturation(image, index, homography, shape, roi)
            sim = np.load(context.path(context.result(f"hologram/{label}/{channel.name}")["simulated"]))
            simulated[index] = torch.from_numpy(sim).square().clamp(0, 1)
        merged = merge_capture(planes, target_roi, saturation=saturation)
        folder = ("images", label + repeat)
        files = {
            "target": write_linear16(context.path(*folder, "target.png"), target_roi.square(), srgb=True),
            "capture": write_linear16(context.path(*folder, "capture.png"), merged.merged_linear, srgb=True),
            "capture_linear": write_linear16(context.path(*folder, "capture-linear.png"), merged.merged_linear),
            "simulated": write_linear16(context.path(*folder, "simulated.png"), simulated, srgb=True),
        }
        names = {target_plane(c): c.name for c in lit}
        for index, plane in planes.items():
            peak = float(max(plane.max(), 1e-12))
            files[f"plane_{names[index]}"] = write_linear16(context.path(*folder, f"plane-{names[index]}.png"),
                                                            np.clip(plane, 0, None) / peak)
        per_colour = {}
        for channel in lit:
            index = target_plane(channel)
            generated = context.result(f"hologram/{label}/{channel.name}")
            per_colour[channel.name] = {
                "capture": {k: round(v, 4) for k, v in merged.scores[index].items()},
                "simulated": generated["scores"], "generation_s": generated["seconds"],
                "cached": generated["cached"], "gain": merged.gains[index], "saturated_fraction": saturation[index],
                "power_w": context.result(f"capture/{label}{repeat}/{channel.name}")["setpoint_w"],
                "peak": round(float(np.percentile(planes[index], PEAK_PERCENTILE)), 4),
            }
        return {
            "target": spec, "method": method, "label": label + repeat, "folder": "/".join(folder), "files": files,
            "colours": per_colour, "warnings": list(merged.warnings),
            "merged": {"capture": {k: round(v, 4) for k, v in merged.merged_scores.items()},
                       "simulated": {k: round(v, 4) for k, v in colour_scores(simulated, target_roi).items()}},
        }

    return action


def _reporter(targets: list[tuple[str, str, list[LaserChannel]]], used: list[LaserChannel]):
    def action(context: Context) -> dict[str, Any]:
        results = [context.result(f"process/{label}{repeat}")
                   for _, label, _ in targets
                   for repeat in _repeats(context.parameters(ColourCaptureParameters).repeats)]
        return colour_capture_report(context, results, [c.name for c in used])

    return action
