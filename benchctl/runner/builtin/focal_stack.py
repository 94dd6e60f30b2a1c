"""Focal-stack capture: a 3D hologram judged the way an eye sees it (docs/focal_stack.md).

Per scene with depth (`rgbd:...`) and per colour present in it, the hologram of the whole scene at the planes it is
shown at (`planes = "auto"`: those its depth content and the bench's axial resolution need, as `benchctl generate
--planes auto` chooses them; or a count spread evenly over its depth). Then for each plane, nearest the SLM first: the
camera focuses there through the focus calibration's map (every position approached from the side it was calibrated
from, past the backlash), and each colour is exposed alone, RAW frames and dark frames captured. Each plane's captures
are registered onto the target, scored inside that plane's in-focus region (the pixels whose depth lies nearest that
plane; Neural 3D Holography's masks), beside the simulated focal stack of the same hologram, and merged into one colour
image per plane, its colours balanced over that region. The report shows the focal stack plane by plane, simulated
beside captured, with a slider through depth, the per-plane scores and their mean.

Registration is measured first where none is stored (with the camera focused at the target plane); the focus
calibration must be stored (`procedures/focus_calibration.toml`). With exposure = "auto" each colour is probed once at
each plane, focused there, and captured at every plane at the lowest of the powers that put each probe's peak at
`peak_goal`: one power for the colour, so its planes compare, and none of them saturates.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import numpy as np
import torch
from msgspec import Meta

from benchctl.capture.colour_planes import PEAK_PERCENTILE, capture_warnings, captured_amplitude, merge_colours
from benchctl.cgh import get_method, method_names
from benchctl.holograms.depth import scene_planes
from benchctl.memory import Estimate, check_depth_memory, depth_estimate
from benchctl.optics.focal_stack import FocalStackTarget, masked_colour_scores, masked_scores, mean_scores
from benchctl.optics.metrics import centred_slices
from benchctl.optics.planes import MAX_PLANES, PlaneChoice
from benchctl.profiles import LaserChannel
from benchctl.runner.api import (
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
    compute_hologram,
    exposure_cap_w,
    exposure_step,
    figure,
    line_plot,
    load_array,
    load_exposure,
    power_w,
    probe_step,
    probed_power,
    registered,
    registered_saturation,
    row,
    save_array,
    save_hologram,
    save_image,
    shown,
    stepper,
    table,
    target_label,
    target_plane,
    unknown_caps,
    unknown_setpoints,
)
from benchctl.runner.builtin import registration
from benchctl.scenes import is_scene, load_scene, prepare_scene
from benchctl.targets import active_channels

DESCRIPTION = ("per scene with depth and colour, the 3D hologram; per plane, focus there, expose each colour alone, "
               "RAW + dark frames, register, score the in-focus region; merged colour per plane")
OUT_OF_FOCUS_SHADE = 0.25  # the target shown per plane: what is in focus there at full brightness, the rest dimmed


class FocalStackParameters(HologramParameters, kw_only=True):
    """Which scenes, at which planes, with which hologram method; exposure as in colour capture."""

    scenes: Annotated[tuple[str, ...], Meta(min_length=1)] = ("rgbd:three-planes",)
    method: str = "sgd"  # a method that makes holograms of scenes with depth (sgd, dpac)
    # "auto": the planes the scene's depth content and the bench's axial resolution need; a count: that many planes
    # evenly over the scene's lit depth
    planes: Literal["auto"] | Annotated[int, Meta(ge=1, le=MAX_PLANES)] = "auto"
    fit_depth: bool = False  # map a scene file's depth onto the bench's depth range (optics.depth_range_mm)
    registration: RegistrationMode = "auto"
    exposure: ExposureMode = "auto"  # "auto": one probe per colour sets the power for all its planes; "fixed"
    peak_goal: PeakGoal = 0.7
    max_exposure_power: ExposureCap = None  # the most "auto" may set: "5mW", "10%" or per colour; default max_power_mw


PARAMETERS = FocalStackParameters


@dataclass(frozen=True, eq=False)
class StackScene:
    """A scene with depth on the bench: its spec and file label, the target amplitude (3, H, W) and depth (H, W) on
    the SLM grid, the planes it is shown at and why, the colours present, and which plane each ROI pixel is in focus
    at (`owner`, (h, w))."""

    spec: str
    label: str
    amplitude: torch.Tensor
    depth_m: torch.Tensor
    planes: PlaneChoice
    lit: tuple[LaserChannel, ...]
    owner: torch.Tensor
    roi: tuple[slice, slice]
    note: str | None
    memory: Estimate  # one colour's hologram of it

    @property
    def target_roi(self) -> torch.Tensor:
        """The target amplitude on the ROI (3, h, w), the colours not captured black: a run of some colours is
        scored on those."""
        chosen = torch.zeros(3, 1, 1, dtype=self.amplitude.dtype)
        chosen[[target_plane(c) for c in self.lit]] = 1
        return self.amplitude[:, self.roi[0], self.roi[1]] * chosen

    def region(self, k: int) -> torch.Tensor:
        """Plane k's in-focus region on the ROI (h, w, bool)."""
        return self.owner == k


def stack_scene(context: Context, spec: str, label: str, planes: int | None, fit_depth: bool,
                used: list[LaserChannel], key: str = "parameters.scenes",
                advice: str = "parameters.planes = {}") -> StackScene:
    """`spec` put on the bench: loaded, prepared on the SLM grid, its planes chosen (None: auto) for the colours of
    `used` present in it, their hologram's memory checked (a refusal says, with `advice`, how many fixed planes fit);
    errors name the parameter `key`."""
    profile = context.profile
    slm, optics = profile.section("slm"), profile.section("optics")
    if not is_scene(spec):
        raise BenchctlError(f"{key}: {spec!r} is not a scene with depth (rgbd:<name> or rgbd:<file>.toml; "
                            "`benchctl targets` lists them)")
    try:
        loaded = load_scene(spec, optics.roi, optics.depth_range_m, fit_depth=fit_depth)
    except BenchctlError as exc:
        raise BenchctlError(f"{key}: {exc}") from None
    amplitude, depth = prepare_scene(loaded, slm.shape, optics.roi)
    present = active_channels(amplitude)
    lit = tuple(c for c in used if present[target_plane(c)])
    if not lit:
        raise BenchctlError(f"{key}: {spec!r} has none of the colours {[c.name for c in used]}")
    rows, cols = centred_slices(slm.shape, optics.roi)
    light = sum((amplitude[target_plane(c), rows, cols].square() for c in lit), torch.zeros(optics.roi))
    choice = scene_planes(depth[rows, cols], light, context.bench.setups([c.name for c in lit]), planes)
    memory = depth_estimate(profile, len(choice.depths_m), len(choice.planes_m), len(used))
    check_depth_memory(memory, f"{key}: {spec}", advice)
    masks = FocalStackTarget(amplitude[target_plane(lit[0])], depth, choice.planes_m).masks
    return StackScene(spec, label, amplitude, depth, choice, lit, masks[:, rows, cols].argmax(0), (rows, cols),
                      loaded.note, memory)


def plan(context: Context) -> list[Step]:
    """Registration if needed; per scene: holograms, probes, per plane a focused exposure per colour and the plane's
    scores; the report."""
    params = context.parameters(FocalStackParameters)
    unknown_setpoints(context)
    unknown_caps(context, params.max_exposure_power)
    context.profile.require("focus", "camera", "slm", "optics", "laser")
    used = channels(context)
    check_method(context, used)
    count = None if params.planes == "auto" else params.planes
    labels: set[str] = {registration.LABEL}
    scenes = [stack_scene(context, spec, scene_label(spec, labels), count, params.fit_depth, used)
              for spec in params.scenes]
    stacks = [step for scene in scenes for step in stack_steps(context, scene, params, params.exposure,
                                                               params.peak_goal, params.max_exposure_power)]
    # (planning the stacks checked the focus calibration before registration is planned)
    lit = [c for c in used if any(c in s.lit for s in scenes)]
    return [*registration.registration_first(context, lit, params, params.registration), *stacks,
            Step("report", "metrics.json, metrics.csv and report.html", _reporter(scenes))]


def stack_steps(context: Context, scene: StackScene, options: HologramParameters, exposure: str,
                peak_goal: float, cap: ExposureCap = None) -> list[Step]:
    """One scene: a hologram per colour as `options` say, the probes (`exposure` "auto": one per colour and plane,
    aiming at `peak_goal`, never above `cap`, a procedure's `max_exposure_power`), then per plane each colour focused
    and exposed, and the plane's scores."""
    label, planes = scene.label, scene.planes.planes_m
    if len(planes) > 1 and get_method(options.method).focal_stack is None:
        able = ", ".join(name for name in method_names() if get_method(name).focal_stack is not None)
        raise BenchctlError(f"parameters.method: {options.method!r} makes holograms of one plane; {scene.spec} is "
                            f"shown on {len(planes)} planes and needs one of: {able}")
    steps = [Step(f"hologram/{label}/{c.name}", f"3D hologram {label} {c.name} ({options.method}, {len(planes)} "
                  f"plane(s))", _hologram(scene, c, options), memory=scene.memory) for c in scene.lit]
    powers: dict[str, Any] = {c.name: power_w(context, c) for c in scene.lit}
    caps = {c.name: exposure_cap_w(context, c, cap) for c in scene.lit}
    if exposure == "auto":
        for channel in scene.lit:
            probes, powers[channel.name] = plane_probes(context, f"probe/{label}/{channel.name}", channel,
                                                        shown(f"hologram/{label}/{channel.name}"), planes, peak_goal,
                                                        f"probe exposure {label}", caps[channel.name])
            steps += probes
    for k, depth in enumerate(planes):
        where = f"plane {k + 1}/{len(planes)} ({depth * 1e3:.2f} mm)"
        for channel in scene.lit:
            steps.append(exposure_step(context, _capture_key(label, k, channel), channel, powers[channel.name],
                                       shown(f"hologram/{label}/{channel.name}"), f"expose {label} {where}",
                                       max_w=caps[channel.name], depth_m=depth))
        steps.append(Step(f"process/{label}/plane-{k + 1}", f"register, merge and score {label} {where}",
                          _processor(scene, k)))
    steps.append(Step(f"stack/{label}", f"the focal stack of {label}: its scores over the planes",
                      _summariser(scene, options)))
    return steps


def scene_label(spec: str, taken: set[str]) -> str:
    """A short file-name label for a scene with depth (rgbd:three-planes -> three-planes), unique in `taken`."""
    return target_label(spec.removeprefix("rgbd:"), taken)


def plane_probes(context: Context, key: str, channel: LaserChannel, frame: Callable[[Context], np.ndarray],
                 planes_m: Sequence[float], peak_goal: float, what: str,
                 max_w: float | None = None) -> tuple[list[Step], Callable[[Context], float]]:
    """Automatic exposure of a focal stack: one probe of `frame` per plane, focused there (steps `<key>/plane-<k>`),
    and the power of every capture of the stack: the lowest the probes chose (read when a capture runs), so that
    the planes compare and none saturates; at most `max_w` (`exposure_cap_w`; None: the channel's max_power_mw)."""
    keys = [f"{key}/plane-{k + 1}" for k in range(len(planes_m))]
    steps = [probe_step(context, probe, channel, frame, f"{what} at plane {k + 1}", peak_goal, max_w, depth_m=depth)
             for k, (probe, depth) in enumerate(zip(keys, planes_m))]
    return steps, lambda context: min(probed_power(probe)(context) for probe in keys)


def _capture_key(label: str, k: int, channel: LaserChannel) -> str:
    return f"capture/{label}/plane-{k + 1}/{channel.name}"


def _rounded(scores: dict[str, float] | None) -> dict[str, float] | None:
    return None if scores is None else {key: round(value, 4) for key, value in scores.items()}


def _hologram(scene: StackScene, channel: LaserChannel, options: HologramParameters):
    def action(context: Context) -> dict[str, Any]:
        result = compute_hologram(context, scene.amplitude, channel, options, depth_m=scene.depth_m,
                                  planes=scene.planes)
        cached = "cached" if result.cached else f"{result.seconds:.2f} s"
        context.say(f"      {options.method} {channel.name}: {cached}, simulated mean in-focus PSNR "
                    f"{result.scores['psnr_amplitude_db']:.2f} dB amplitude over {len(scene.planes.planes_m)} plane(s)")
        return {"file": save_hologram(context, result.gray, f"{scene.label}-{channel.name}.png"),
                "seconds": round(result.seconds, 4), "cached": result.cached, "scores": _rounded(result.scores),
                "plane_scores": [_rounded(s) for s in result.plane_scores or [result.scores]],
                "simulated": save_array(context, result.reconstruction, scene.label, f"simulated-{channel.name}.npy")}

    return action


def _processor(scene: StackScene, k: int):
    def action(context: Context) -> dict[str, Any]:
        target, region, label = scene.target_roi, scene.region(k), scene.label
        signals, saturation, simulated, colours = {}, {}, {}, {}
        for channel in scene.lit:
            index, key = target_plane(channel), _capture_key(label, k, channel)
            image, _ = load_exposure(context, key)
            signals[index] = registered(context, image, channel)
            saturation[index] = registered_saturation(context, image, channel)
            generated = context.result(f"hologram/{label}/{channel.name}")
            simulated[index] = torch.from_numpy(load_array(context, generated["simulated"])[k])
            capture = context.result(key)
            colours[channel.name] = {
                "capture": _rounded(masked_scores(captured_amplitude(signals[index]), target[index], region)),
                "simulated": generated["plane_scores"][k], "power_w": capture["setpoint_w"],
                "focus": capture.get("focus"), "saturated_fraction": round(saturation[index], 6),
                "peak": round(float(np.percentile(signals[index], PEAK_PERCENTILE)), 4)}
        captured = merge_colours({i: captured_amplitude(s) for i, s in signals.items()}, target, region)
        modelled = merge_colours(simulated, target, region)
        plane = f"plane-{k + 1}"
        shade = torch.where(region, 1.0, OUT_OF_FOCUS_SHADE)
        files = {"target": save_image(context, target.square() * shade, label, f"{plane}-target.png", srgb=True),
                 "simulated": save_image(context, modelled.linear, label, f"{plane}-simulated.png", srgb=True),
                 "capture": save_image(context, captured.linear, label, f"{plane}-capture.png", srgb=True)}
        return {"plane": k + 1, "depth_mm": round(scene.planes.planes_m[k] * 1e3, 6),
                "in_focus": round(float(region.float().mean()), 4), "colours": colours, "files": files,
                "capture": _rounded(mean_scores([c["capture"] for c in colours.values()])) or None,
                "simulated": _rounded(mean_scores([c["simulated"] for c in colours.values()])) or None,
                "merged": {"capture": _rounded(masked_colour_scores(captured.linear, target, region)),
                           "simulated": _rounded(masked_colour_scores(modelled.linear, target, region))},
                "gains": {c.name: round(captured.gains[target_plane(c)], 6) for c in scene.lit},
                "warnings": capture_warnings(signals, target, saturation)}

    return action


def _summariser(scene: StackScene, options: HologramParameters):
    def action(context: Context) -> dict[str, Any]:
        """The scene's focal stack from its planes' results: the planes and why, each plane's result, and the means
        over the planes with an in-focus region (amplitude PSNR and SSIM, each plane's the mean over its colours)."""
        planes = [context.result(f"process/{scene.label}/plane-{k + 1}") for k in range(len(scene.planes.planes_m))]
        model = "fitted" if options.optical_model == "fitted" and context.profile.section("optics").model else "ideal"
        return {"scene": scene.spec, "label": scene.label, "note": scene.note, "planes_reason": scene.planes.reason,
                "method": options.method, "iterations": options.iterations, "optical_model": model, "planes": planes,
                "mean": {kind: _rounded(mean_scores([p[kind] for p in planes])) for kind in ("capture", "simulated")},
                "merged_mean": {kind: _rounded(mean_scores([p["merged"][kind] for p in planes]))
                                for kind in ("capture", "simulated")}}

    return action


def _reporter(scenes: list[StackScene]):
    def action(context: Context) -> dict[str, Any]:
        return focal_stack_report(context, [context.result(f"stack/{scene.label}") for scene in scenes],
                                  sorted({c.name for s in scenes for c in s.lit}))

    return action


def _db(scores: dict[str, float] | None, key: str = "psnr_amplitude_db") -> float | None:
    return None if not scores else scores.get(key)


def focal_stack_sections(report: Report, context: Context, summary: dict[str, Any]) -> list[dict[str, Any]]:
    """A scene's sections of a report: the per-plane table with the means, PSNR against depth, and the focal stack
    (target in focus, simulated, captured) one row per plane with a slider through depth; returns its CSV rows."""
    label, planes = summary["label"], summary["planes"]
    rows, csv = [], []
    for plane in planes:
        rows.append({"plane": plane["plane"], "depth mm": plane["depth_mm"], "in focus": plane["in_focus"],
                     **{f"{name} focus steps": (colour.get("focus") or {}).get("steps")
                        for name, colour in plane["colours"].items()},
                     "simulated PSNR dB": _db(plane["simulated"]), "captured PSNR dB": _db(plane["capture"]),
                     "simulated SSIM": _db(plane["simulated"], "ssim_amplitude"),
                     "captured SSIM": _db(plane["capture"], "ssim_amplitude"),
                     "captured merged PSNR dB sRGB": _db(plane["merged"]["capture"], "psnr_srgb_db")})
        report.warn(*[f"{label} plane {plane['plane']}: {w}" for w in plane["warnings"]])
        for name, colour in plane["colours"].items():
            csv.append({"scene": summary["scene"], "plane": plane["plane"], "depth_mm": plane["depth_mm"],
                        "colour": name, **{f"simulated_{k}": v for k, v in (colour["simulated"] or {}).items()},
                        **{f"capture_{k}": v for k, v in (colour["capture"] or {}).items()}})
    mean = summary["mean"]
    rows.append({"plane": "mean", "simulated PSNR dB": _db(mean["simulated"]), "captured PSNR dB": _db(mean["capture"]),
                 "simulated SSIM": _db(mean["simulated"], "ssim_amplitude"),
                 "captured SSIM": _db(mean["capture"], "ssim_amplitude"),
                 "captured merged PSNR dB sRGB": _db(summary["merged_mean"]["capture"], "psnr_srgb_db")})
    csv.append({"scene": summary["scene"], "plane": "mean", "colour": "all",
                **{f"simulated_{k}": v for k, v in (mean["simulated"] or {}).items()},
                **{f"capture_{k}": v for k, v in (mean["capture"] or {}).items()}})
    scored = [p for p in planes if p["capture"] and p["simulated"]]
    depths = [float(p["depth_mm"]) for p in scored]
    curves = {kind: (depths, [float(p[key]["psnr_amplitude_db"]) for p in scored])
              for kind, key in (("simulated", "simulated"), ("captured", "capture"))}
    frames = [(f"plane {p['plane']} of {len(planes)}: {p['depth_mm']:.2f} mm",
               row(figure(context, p["files"]["target"], f"target, in focus at {p['depth_mm']:.2f} mm (the rest "
                                                         "dimmed)"),
                   figure(context, p["files"]["simulated"], f"simulated at {p['depth_mm']:.2f} mm"),
                   figure(context, p["files"]["capture"], f"captured at {p['depth_mm']:.2f} mm"))) for p in planes]
    note = (f"<p>{summary['method']} hologram through the {summary['optical_model']} optical model; "
            f"{summary['planes_reason']}. Each plane is scored inside its in-focus region (the pixels whose depth lies "
            "nearest that plane), amplitude PSNR and SSIM after a least-squares scale, each the mean over the "
            "colours; merged: the colour image with each colour balanced over that region, PSNR in sRGB. The mean "
            "is over the planes.</p>")
    report.section(f"Scene {summary['scene']} ({label})", note, table(rows),
                   line_plot(curves, "plane depth (mm from the SLM)", "in-focus PSNR dB (amplitude)") if depths else "")
    report.section("Focal stack", stepper(label, frames, "depth"), level=3)
    return csv


def focal_stack_report(context: Context, summaries: list[dict[str, Any]], colours: list[str]) -> dict[str, Any]:
    """The focal-stack report: per scene its sections (`focal_stack_sections`); metrics.json and metrics.csv."""
    report = Report(f"Focal stack: {', '.join(s['label'] for s in summaries)}")
    csv: list[dict[str, Any]] = []
    for summary in summaries:
        csv += focal_stack_sections(report, context, summary)
    return report.write(context, {"procedure": "focal-stack", "scenes": summaries}, csv, colours,
                        [stack_headline(s) for s in summaries])


def stack_headline(summary: dict[str, Any]) -> str:
    """A scene's line at the end of a run: its mean in-focus PSNR captured and simulated (every pixel is in focus at
    some plane, so the means exist)."""
    mean = summary["mean"]
    return (f"{summary['label']}: mean in-focus PSNR {mean['capture']['psnr_amplitude_db']:.2f} dB captured, "
            f"{mean['simulated']['psnr_amplitude_db']:.2f} dB simulated (amplitude, over {len(summary['planes'])} "
            f"plane(s), {summary['method']}, {summary['optical_model']} optical model)")
