"""`benchctl bench depth`: how many planes a scene with depth needs, measured.

Per bundled scene, a method (SGD by default) makes the scene's hologram at K = 1 .. 16 planes spread evenly over
the scene's lit depth, and at the planes `--planes auto` chooses; every hologram is judged the same way, on what a
viewer sees focusing on each point of the scene in turn: the all-in-focus image, each pixel taken from a dense
focal stack (64 planes evenly over the scene's depth) at the plane nearest its own depth, its amplitude PSNR after
one least-squares scale. A judge finer than any K, so that no K is judged at exactly its own planes; the curve of
that PSNR against K shows what more planes buy and what they cost. The two-plane check follows: multi-plane SGD's
in-focus PSNR on each plane of rgbd:two-planes against 2D SGD on that plane's image alone at the same iterations;
then the flat-scene check against 2D. One colour, the profile's optics (its fitted model where it has one),
no SLM quantisation: the hologram method and the planes are what is measured.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Sequence
from typing import Any, Callable

import torch

from benchctl.benchmarks.speed_vs_error import size_refusal
from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.setups import optical_setup
from benchctl.cgh import get_method
from benchctl.holograms.depth import compute_depth_scene, scene_planes
from benchctl.holograms.scene import compute_scene
from benchctl.memory import check_depth_memory, depth_estimate
from benchctl.optics.focal_stack import FocalStackTarget, focal_stack_scores
from benchctl.optics.focal_stack import all_in_focus_psnr as stack_all_in_focus_psnr
from benchctl.optics.metrics import centred_slices
from benchctl.optics.planes import PlaneChoice, even_planes
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile
from benchctl.scenes import list_scenes, load_scene, prepare_scene
from benchctl.targets import load_target, prepare_target, target_plane

DEFAULT_SCENES = tuple(list_scenes())
EVALUATION_PLANES = 64
TIE_DB = 0.1
"""Plane counts whose PSNR lies within this of the highest count as the best: the fewest of them is "the best K"."""
AUTO = "auto"


def _timed(device: torch.device, fn: Callable[..., torch.Tensor], *args: Any,
           **kwargs: Any) -> tuple[torch.Tensor, float]:
    """`fn(*args, **kwargs)` and the seconds it took, the device synchronised around it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    result = fn(*args, **kwargs)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return result, time.perf_counter() - start


def _stack_psnr(setup: OpticalSetup, phase: torch.Tensor, target: FocalStackTarget) -> list[float | None]:
    """Per plane of `target`, the in-focus amplitude PSNR of `phase`'s focal stack there."""
    rows, cols = setup.roi_slices
    scores = focal_stack_scores(_stack(setup, phase, target.planes_m).cpu(), target.amplitude[rows, cols].cpu(),
                                target.masks[:, rows, cols].cpu(), target.planes_m)
    return [None if s is None else s["psnr_amplitude_db"] for s in scores.per_plane]


def _stack(setup: OpticalSetup, phase: torch.Tensor, planes_m: tuple[float, ...]) -> torch.Tensor:
    if len(planes_m) == 1:
        return setup.at_distance(planes_m[0]).reconstruct_roi(phase)[None]
    with torch.no_grad():
        return setup.reconstruct_planes_roi(phase, planes_m)


def all_in_focus_psnr(setup: OpticalSetup, phase: torch.Tensor, judge: FocalStackTarget) -> float:
    """Amplitude PSNR of the all-in-focus image of `phase` (`focal_stack.all_in_focus_psnr`) at the planes of
    `judge`, on the ROI."""
    rows, cols = setup.roi_slices
    return stack_all_in_focus_psnr(_stack(setup, phase, judge.planes_m), judge.amplitude[rows, cols],
                                   judge.masks[:, rows, cols].argmax(dim=0))


def run_depth_bench(
    profile: Profile,
    scenes: Sequence[str] = DEFAULT_SCENES,
    counts: Sequence[int] = tuple(range(1, 17)),
    *,
    method: str = "sgd",
    iterations: int | None = 100,
    colour: str = "green",
    seed: int = 0,
    device: str | torch.device = "cpu",
    out: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Print and return one row per scene and plane count (K, or "auto"): planes, seconds, focal-stack PSNR on the
    judging stack; then per scene the best K, the chosen one and whether the chosen is within 0.5 dB of the best at
    no more than half its time; then the two-plane check on rgbd:two-planes where it is among `scenes`."""
    device = torch.device(device)
    generate = get_method(method)
    if generate.default_iterations is None:
        iterations = None  # a one-shot method
    slm, optics = profile.section("slm"), profile.section("optics")
    grid, roi = slm.shape, optics.roi
    setup = optical_setup(profile, colour)
    rows, cols = centred_slices(grid, roi)
    channel_plane = target_plane(profile.channel(colour))
    out(f"grid {grid[0]}x{grid[1]}, ROI {roi[0]}x{roi[1]}, distance {optics.distance_mm:g} mm, depth range "
        f"{optics.depth_range_mm}, {colour}, {method} {_budget(iterations)}, device {device}; judged on the "
        f"all-in-focus image from {EVALUATION_PLANES} planes evenly over each scene's depth")
    planned = []
    for spec in scenes:  # every scene's planes chosen and their memory checked before any is computed
        amplitude, depth = prepare_scene(load_scene(spec, roi, optics.depth_range_m), grid, roi)
        amplitude, depth = amplitude[channel_plane].to(device), depth.to(device)
        light = amplitude[rows, cols].square()
        auto = scene_planes(depth[rows, cols], light, {colour: setup}, None)
        choices: list[tuple[int | str, PlaneChoice]] = [(k, even_planes(depth[rows, cols], light, k)) for k in counts]
        choices.append((AUTO, auto))
        for _, choice in choices:
            check_depth_memory(depth_estimate(profile, len(choice.depths_m), len(choice.planes_m)),
                               *size_refusal(profile, spec))
        judging = even_planes(depth[rows, cols], light, EVALUATION_PLANES)
        planned.append((spec, amplitude, depth, judging, auto, choices))
    results: list[dict[str, Any]] = []
    for spec, amplitude, depth, judge_planes, auto, choices in planned:
        judge = FocalStackTarget(amplitude, depth, judge_planes.planes_m)  # masks: the nearest judging plane
        warm_up = 2 if generate.default_iterations is not None else None  # kernels and caches built outside the timing
        generate(FocalStackTarget(amplitude, depth, auto.planes_m, sweep=auto.sweep), setup, iterations=warm_up)
        seen: set[tuple[float, ...]] = set()
        for count, choice in choices:
            if count != AUTO and choice.planes_m in seen:
                continue  # a flat scene: every K is one plane
            seen.add(choice.planes_m)
            target = FocalStackTarget(amplitude, depth, choice.planes_m, sweep=choice.sweep)
            phase, seconds = _timed(device, generate, target, setup, iterations=iterations, seed=seed)
            score = all_in_focus_psnr(setup, phase, judge)
            results.append({"scene": spec, "planes": count, "planes_m": choice.planes_m, "count": len(choice.planes_m),
                            "seconds": seconds, "psnr_db": score})
        _summarise(spec, [r for r in results if r["scene"] == spec], auto, out)
    if "rgbd:two-planes" in scenes:
        results += _two_plane_check(profile, setup, channel_plane, generate.name, iterations, seed, device, out)
    if "rgbd:flat" in scenes and device.type == "cpu":
        results.append(flat_scene_check(profile, generate.name, iterations, colour, out=out))
    return results


def flat_scene_check(profile: Profile, method: str, iterations: int | None, colour: str, *, repeats: int = 5,
                     out: Callable[[str], None] = print) -> dict[str, Any]:
    """rgbd:flat (a Siemens star on one plane, the middle of the depth range) with --planes auto against
    chart:siemens in 2D at that plane, in turn `repeats` times: both loaded, prepared and computed as generate
    computes them (the displayed hologram and its scores, without the perceptual scores); whether the holograms are
    the same, and the medians of the per-round time ratios, the hologram alone and the whole."""
    slm, optics = profile.section("slm"), profile.section("optics")
    grid, roi = slm.shape, optics.roi
    plane = float(load_scene("rgbd:flat", (1, 1), optics.depth_range_m).depth_m[0, 0])
    bench = Calibrated(profile)
    at_plane = bench.at_distance(plane)  # the profile's distance, unless scaled
    ratios_hologram, ratios_total = [], []
    for _ in range(repeats + 1):  # the first round warms up
        start = time.perf_counter()
        flat = compute_scene(prepare_target(load_target("chart:siemens", roi), grid, roi), at_plane, method,
                             iterations=iterations, colours=[colour])
        flat_total = time.perf_counter() - start
        start = time.perf_counter()
        amplitude, depth = prepare_scene(load_scene("rgbd:flat", roi, optics.depth_range_m), grid, roi)
        deep = compute_depth_scene(amplitude, depth, bench, method, iterations=iterations, colours=[colour],
                                   perceptual=False, refusal=size_refusal(profile, "rgbd:flat"))
        deep_total = time.perf_counter() - start
        ratios_hologram.append(deep.colours[0].seconds / flat.colours[0].seconds)
        ratios_total.append(deep_total / flat_total)
    same = flat.colours[0].gray is not None and deep.colours[0].gray is not None and bool(
        (flat.colours[0].gray == deep.colours[0].gray).all())
    psnr_2d, psnr_3d = flat.colours[0].scores["psnr_amplitude_db"], deep.mean_scores["psnr_amplitude_db"]
    hologram, total = statistics.median(ratios_hologram[1:]), statistics.median(ratios_total[1:])
    out("")
    out(f"rgbd:flat --planes auto against chart:siemens in 2D ({method}, {colour}, {repeats} rounds): "
        f"{len(deep.planes.planes_m)} plane; same hologram: {'yes' if same else 'NO'}; PSNR {psnr_3d:.3f} dB against "
        f"{psnr_2d:.3f} dB; time 3D / 2D: hologram {hologram:.3f}, with loading and scoring {total:.3f} "
        f"(goal within 5 %: {'met' if total <= 1.05 else 'NOT met'})")
    return {"scene": "rgbd:flat", "check": "flat", "same_hologram": same, "psnr_2d_db": psnr_2d, "psnr_3d_db": psnr_3d,
            "hologram_time_ratio": hologram, "total_time_ratio": total}


def _budget(iterations: int | None) -> str:
    return "one shot" if iterations is None else f"at {iterations} iterations"


def _summarise(spec: str, rows: list[dict[str, Any]], auto: PlaneChoice, out: Callable[[str], None]) -> None:
    out("")
    out(f"{spec}: auto: {auto.reason}")
    out(f"  {'K':>5} {'planes':>6} {'seconds':>8} {'all-in-focus PSNR dB':>21}")
    for row in rows:
        out(f"  {row['planes']!s:>5} {row['count']:>6} {row['seconds']:>8.2f} {row['psnr_db']:>21.2f}")
    fixed = [r for r in rows if r["planes"] != AUTO]
    if not fixed:
        return
    top = max(r["psnr_db"] for r in fixed)
    # the fewest planes within TIE_DB of the top: planes with nothing in focus change the PSNR by hundredths
    best = min((r for r in fixed if r["psnr_db"] >= top - TIE_DB), key=lambda r: r["count"])
    chosen = next(r for r in rows if r["planes"] == AUTO)
    if chosen["planes_m"] == best["planes_m"]:
        out(f"  auto chose the best K: {best['count']} plane(s), {best['psnr_db']:.2f} dB")
        return
    within = best["psnr_db"] - chosen["psnr_db"] <= 0.5
    cheaper = chosen["seconds"] <= 0.5 * best["seconds"]
    out(f"  best K {best['planes']} ({best['psnr_db']:.2f} dB, {best['seconds']:.2f} s); auto {chosen['count']} "
        f"plane(s): {chosen['psnr_db'] - best['psnr_db']:+.2f} dB from the best "
        f"({'within' if within else 'NOT within'} 0.5 dB), {chosen['seconds'] / best['seconds']:.2f}x its time"
        f" ({'at most' if cheaper else 'more than'} half)")


def _two_plane_check(profile: Profile, setup: OpticalSetup, channel_plane: int, method: str,
                     iterations: int | None, seed: int, device: torch.device,
                     out: Callable[[str], None]) -> list[dict[str, Any]]:
    """Multi-plane SGD on rgbd:two-planes against 2D SGD on each plane's image alone, at the same iterations."""
    optics, grid = profile.section("optics"), profile.section("slm").shape
    rows, cols = centred_slices(grid, optics.roi)
    amplitude, depth = prepare_scene(load_scene("rgbd:two-planes", optics.roi, optics.depth_range_m), grid, optics.roi)
    amplitude, depth = amplitude[channel_plane].to(device), depth.to(device)
    planes = scene_planes(depth[rows, cols], amplitude[rows, cols].square(), {"": setup}, None).planes_m
    target = FocalStackTarget(amplitude, depth, planes)
    generate = get_method(method)
    stack = _stack_psnr(setup, generate(target, setup, iterations=iterations, seed=seed), target)
    out("")
    out(f"rgbd:two-planes, {method} {_budget(iterations)}: in-focus PSNR per plane, the focal stack against 2D on the "
        "plane's image alone")
    found = []
    for k, plane in enumerate(planes):
        alone = generate(amplitude * target.masks[k], setup.at_distance(plane), iterations=iterations, seed=seed)
        flat = _stack_psnr(setup, alone, target)
        gap = (stack[k] or 0.0) - (flat[k] or 0.0)
        out(f"  plane {k + 1} at {plane * 1e3:.3f} mm: focal stack {stack[k]:.2f} dB, 2D alone {flat[k]:.2f} dB "
            f"({gap:+.2f} dB; goal within 2 dB: {'met' if gap >= -2 else 'NOT met'})")
        found.append({"scene": "rgbd:two-planes", "check": "two-plane", "plane_m": plane, "stack_psnr_db": stack[k],
                      "alone_psnr_db": flat[k]})
    return found
