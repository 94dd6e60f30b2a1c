"""Holograms for a colour scene with depth: the planes it needs, one method per emitting colour, the displayed phase,
the simulated focal stack and its per-plane scores, and the all-in-focus PSNR at the depths the hologram is meant to
be seen at (its planes, or a sweep's depths: a swept hologram is in focus between its planes, where the per-plane
scores, which ask every pixel near a plane to be sharp there, count its natural defocus as error).

The depth twin of `holograms.scene.compute_scene`, shared by `benchctl generate rgbd:...` and `benchctl bench
speed-vs-error`; it writes no files. A scene that needs one plane is computed and scored as 2D at that plane.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch

from benchctl.calibration.calibrated import Calibrated
from benchctl.errors import BenchctlError
from benchctl.holograms.scene import ColourResult, resolve_method, select_channels
from benchctl.memory import check_depth_memory, depth_estimate
from benchctl.optics.focal_stack import (FocalStackTarget, all_in_focus_psnr, focal_stack_scores, mean_scores,
                                         nearest_plane, scaled_psnr, stack_scale)
from benchctl.optics.metrics import centred_slices
from benchctl.optics.planes import PlaneChoice, choose_planes, even_planes, finest_resolution_m
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import LaserChannel
from benchctl.targets import active_channels, target_plane


@dataclass
class DepthSceneResult:
    """All colours of one scene with depth: the planes and why, each colour's hologram, focal stack (`reconstruction`
    (K, h, w), scaled by the stack's least-squares scale) and scores (`scores`: the mean over planes,
    `plane_scores`: per plane), the merged colour focal stack and the per-plane scores averaged over colours."""

    method: str
    iterations: int | None
    planes: PlaneChoice
    colours: list[ColourResult]
    target_roi: torch.Tensor  # (3, h, w) amplitude
    depth_roi: torch.Tensor  # (h, w) metres
    in_focus: list[float]  # per plane, the share of the ROI in focus there
    stack_linear: torch.Tensor  # (K, 3, h, w) linear intensity
    plane_scores: list[dict[str, float] | None]  # per plane, means over the colours
    mean_scores: dict[str, float]  # means over the planes that have an in-focus region
    checkpoint: Path | None = None


def focal_stack_roi(setup: OpticalSetup, phase: torch.Tensor, planes_m: tuple[float, ...]) -> torch.Tensor:
    """The focal stack (K, h, w) of `phase` on the ROI; one plane exactly as 2D reconstructs it at that distance."""
    if len(planes_m) == 1:
        return setup.at_distance(planes_m[0]).reconstruct_roi(phase)[None]
    return setup.reconstruct_planes_roi(phase, planes_m)


JUDGE_CHUNK = 16
"""Depths of a sweep propagated at once to make its all-in-focus image."""


def swept_image(setup: OpticalSetup, phase: torch.Tensor, depths_m: tuple[float, ...],
                depth_roi: torch.Tensor) -> torch.Tensor:
    """The all-in-focus amplitude (h, w) on the ROI of `phase` over a sweep's depths: each pixel at the depth nearest
    its own (`nearest_plane`), the depths propagated JUDGE_CHUNK at a time through the sweep's cached propagator: all
    of a deep sweep's at once held more memory than its optimisation (docs/depth.md)."""
    owner = nearest_plane(depth_roi, depths_m)
    image = torch.zeros(owner.shape, dtype=torch.promote_types(phase.dtype, torch.float32))
    for start in range(0, len(depths_m), JUDGE_CHUNK):
        pick = list(range(start, min(start + JUDGE_CHUNK, len(depths_m))))
        planes = setup.reconstruct_planes_roi(phase, depths_m, pick)
        for plane, k in zip(planes, pick):
            mine = owner == k
            image[mine] = plane[mine]
    return image


def scene_planes(depth_m: torch.Tensor, light: torch.Tensor, setups: Mapping[str, OpticalSetup],
                 planes: int | Sequence[float] | PlaneChoice | None) -> PlaneChoice:
    """`planes` evenly over the lit depth (a count), exactly those planes (distances in metres, or the choice itself
    with its sweep, as a procedure that chose them for every colour gives them), or (None: auto) the planes the depth
    content and the finest axial resolution of the colours' setups need (`choose_planes`)."""
    if isinstance(planes, PlaneChoice):
        return planes
    if isinstance(planes, Sequence):
        chosen = tuple(sorted(float(z) for z in planes))
        return PlaneChoice(chosen, f"{len(chosen)} plane(s) at {', '.join(f'{z * 1e3:.2f}' for z in chosen)} mm, "
                                   "as given")
    if planes is not None:
        return even_planes(depth_m, light, planes)
    return choose_planes(depth_m, light, finest_resolution_m([s.geometry for s in setups.values()]))


def depth_scene_planes(
    target_amplitude: torch.Tensor,
    depth_m: torch.Tensor,
    bench: Calibrated,
    *,
    planes: int | Sequence[float] | PlaneChoice | None = None,
    colours: list[str] | None = None,
    refusal: tuple[str, str | None] | None = None,
) -> tuple[list[LaserChannel], PlaneChoice]:
    """The requested colours a scene lights and the planes `compute_depth_scene` shows it at, their hologram's memory
    checked (not a PlaneChoice's: a procedure checks the planes it chose when it plans them), so that a caller with
    several scenes can refuse before it computes any. `refusal`: what a refusal names and offers
    (`check_depth_memory`'s `what` and `advice`); None: --planes."""
    profile = bench.profile
    grid, roi = profile.section("slm").shape, profile.section("optics").roi
    if tuple(target_amplitude.shape) != (3, *grid) or tuple(depth_m.shape) != tuple(grid):
        raise BenchctlError(f"scene is {tuple(target_amplitude.shape)} with depth {tuple(depth_m.shape)}, the SLM grid "
                            f"needs (3, {grid[0]}, {grid[1]}) and ({grid[0]}, {grid[1]})")
    present = active_channels(target_amplitude)
    lit = [channel for channel in select_channels(profile, colours) if present[target_plane(channel)]]
    rows, cols = centred_slices(grid, roi)
    setups = bench.setups([channel.name for channel in lit] or None)
    light = sum((target_amplitude[target_plane(c), rows, cols].square() for c in lit), torch.zeros(roi))
    choice = scene_planes(depth_m[rows, cols], light, {c.name: setups[c.name] for c in lit} or setups, planes)
    if not isinstance(planes, PlaneChoice):
        check_depth_memory(depth_estimate(profile, len(choice.depths_m), len(choice.planes_m), len(lit) or 1),
                           *(refusal or (f"--planes {planes or 'auto'}", "--planes {}")))
    return lit, choice


def compute_depth_scene(
    target_amplitude: torch.Tensor,
    depth_m: torch.Tensor,
    bench: Calibrated,
    method: str,
    *,
    planes: int | Sequence[float] | PlaneChoice | None = None,
    iterations: int | None = None,
    colours: list[str] | None = None,
    seed: int = 0,
    progress: Callable[[str], Callable[[int, int], None]] | None = None,
    checkpoint: Path | None = None,
    perceptual: bool = True,
    refusal: tuple[str, str | None] | None = None,
) -> DepthSceneResult:
    """Choose the planes, then generate, quantise, display (in simulation) and score a hologram for each requested,
    non-black colour of a scene with depth (`benchctl.scenes.prepare_scene`: amplitude (3, H, W), depth (H, W) in
    metres). `planes`: a number of planes evenly over the scene's lit depth, the planes themselves (metres), or None
    (auto). The rest as
    `compute_scene`; `perceptual` adds FLIP and speckle contrast to the scores; `refusal` as `depth_scene_planes`."""
    profile = bench.profile
    roi = profile.section("optics").roi
    channels = select_channels(profile, colours)
    lit, choice = depth_scene_planes(target_amplitude, depth_m, bench, planes=planes, colours=colours,
                                     refusal=refusal)
    generate, used_checkpoint = resolve_method(method, profile, checkpoint, [c.name for c in lit])
    slm = bench.slm
    rows, cols = centred_slices(profile.section("slm").shape, roi)
    target_roi, depth_roi = target_amplitude[:, rows, cols], depth_m[rows, cols]
    count = len(choice.planes_m)
    stacks: dict[int, torch.Tensor] = {}
    results = []
    previous: OpticalSetup | None = None
    for channel in channels:
        if channel not in lit:
            results.append(ColourResult(channel.name, channel.wavelength_nm, skipped=True))
            continue
        if previous is not None:  # one colour's plane propagators at a time: a sweep's hold GiBs
            previous.release_planes()
        setup = previous = bench.setup(channel.name, as_displayed=True)
        target = FocalStackTarget(target_amplitude[target_plane(channel)], depth_m, choice.planes_m,
                                  sweep=choice.sweep)
        start = time.perf_counter()
        phase = generate(target, setup, iterations=iterations, seed=seed,
                         progress=progress(f"{method} {channel.name}") if progress else None)
        seconds = time.perf_counter() - start
        gray = slm.encode(phase, channel.name)
        shown = torch.from_numpy(slm.driven(gray, channel.name))
        wanted = target_roi[target_plane(channel)]
        if choice.sweep is not None:  # the sweep's transfer functions go before the planes' are made
            seen = scaled_psnr(swept_image(setup, shown, choice.sweep.all_m, depth_roi), wanted)
            setup.release_planes()
        stack = focal_stack_roi(setup, shown, choice.planes_m)
        masks = target.masks[:, rows, cols]
        stack = stack * stack_scale(stack, wanted, masks)
        stacks[target_plane(channel)] = stack
        scores = focal_stack_scores(stack, wanted, masks, choice.planes_m, perceptual=perceptual)
        if choice.sweep is None:  # seen at its planes: each pixel where the per-plane scores take it
            seen = all_in_focus_psnr(stack, wanted, masks.argmax(dim=0))
        scores.mean["all_in_focus_psnr_db"] = seen
        results.append(ColourResult(channel.name, channel.wavelength_nm, skipped=False, seconds=seconds, gray=gray,
                                    reconstruction=stack, scores=scores.mean, plane_scores=scores.per_plane))
    linear = torch.zeros((count, *target_roi.shape), dtype=torch.float32)
    for plane, stack in stacks.items():
        linear[:, plane] = stack.square().clamp(0, 1)
    owner = FocalStackTarget(target_amplitude[0], depth_m, choice.planes_m).masks[:, rows, cols].argmax(0)
    done = [c for c in results if not c.skipped]
    plane_scores = [mean_scores([c.plane_scores[k] for c in done]) or None for k in range(count)]
    in_focus = [c.scores["all_in_focus_psnr_db"] for c in done]
    overall = mean_scores(plane_scores) | ({"all_in_focus_psnr_db": sum(in_focus) / len(in_focus)} if in_focus else {})
    return DepthSceneResult(method, iterations, choice, results, target_roi, depth_roi,
                            [float((owner == k).float().mean()) for k in range(count)], linear, plane_scores,
                            overall, checkpoint=used_checkpoint)

