"""`benchctl generate`: holograms for a target, written exactly as displayed, with reconstruction and metrics."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

import benchctl
from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.files import calibration_used
from benchctl.cgh import DEFAULT_METHOD
from benchctl.files import ensure_dir, write_json
from benchctl.holograms.depth import DepthSceneResult, compute_depth_scene
from benchctl.holograms.scene import SceneResult, compute_scene, select_channels
from benchctl.images import write_png
from benchctl.memory import check_estimates, hologram_estimate
from benchctl.optics import linear_to_srgb
from benchctl.profiles import Profile
from benchctl.provenance import code_identity
from benchctl.scenes import is_scene, load_scene, prepare_scene
from benchctl.targets import load_target, prepare_target


def _srgb8(linear_rgb: torch.Tensor) -> np.ndarray:
    """(3, h, w) linear intensity -> (h, w, 3) 8-bit sRGB."""
    srgb = linear_to_srgb(linear_rgb.clamp(0, 1)).permute(1, 2, 0)
    return (srgb * 255).round().to(torch.uint8).numpy()


def scene_metrics(scene: SceneResult) -> dict[str, Any]:
    """The per-colour and merged figures of a scene, as plain JSON-ready values."""
    colours = {}
    for c in scene.colours:
        colours[c.channel] = {"wavelength_nm": c.wavelength_nm, "skipped": c.skipped}
        if not c.skipped:
            colours[c.channel].update(seconds=round(c.seconds, 4), **{k: round(v, 4) for k, v in c.scores.items()})
    return {
        "method": scene.method,
        "iterations": scene.iterations,
        "checkpoint": str(scene.checkpoint) if scene.checkpoint is not None else None,
        "colours": colours,
        "merged": {k: round(v, 4) for k, v in scene.merged_scores.items()},
    }


def run_generate(
    target: str,
    profile: Profile,
    out_dir: Path,
    *,
    method: str = DEFAULT_METHOD,
    iterations: int | None = None,
    colours: list[str] | None = None,
    seed: int = 0,
    progress: Callable[[str], Callable[[int, int], None]] | None = None,
    checkpoint: Path | None = None,
    planes: int | None = None,
    fit_depth: bool = False,
) -> dict[str, Any]:
    """Generate one hologram per colour present in `target`, write PNGs and metrics.json to `out_dir`.

    A scene with depth (`rgbd:...`, `benchctl.scenes`) is shown at `planes` planes evenly over its depth, or at
    those its depth content needs (None: auto); its focal stack is written as one image per plane, and scored per
    plane (`compute_depth_scene`). `fit_depth` maps a scene file's depth onto the bench's depth range. Either is
    refused before it starts when its estimated memory is above the limit (`benchctl.memory`).

    A learned method uses `checkpoint`, else the one shipped for the profile (see `compute_scene`). What
    calibration/<profile>/ holds is used as a run uses it: the measured lookup tables (for the channels whose
    table the profile does not name) and the fitted optical model.
    """
    started = time.time()
    profile.require("slm", "optics", "laser")  # the laser's channels are the colours generated
    own_tables = profile.section("slm").lut
    bench = Calibrated.stored(profile)
    profile = bench.profile
    slm, optics = profile.section("slm"), profile.section("optics")
    if is_scene(target):
        depth_scene = load_scene(target, optics.roi, optics.depth_range_m, fit_depth=fit_depth)
        amplitude, depth = prepare_scene(depth_scene, slm.shape, optics.roi)
        result = compute_depth_scene(amplitude, depth, bench, method, planes=planes, iterations=iterations,
                                     colours=colours, seed=seed, progress=progress, checkpoint=checkpoint)
        return _write_depth_scene(result, depth_scene.note, Path(out_dir), {
            "benchctl_version": benchctl.__version__, "benchctl_code": code_identity(), "target": target,
            "profile": str(profile.path), "grid": list(slm.shape), "roi": list(optics.roi),
            "optical_model": str(optics.model) if optics.model else None,
            "calibration": calibration_used(profile, own_tables), "seed": seed, "started_unix": round(started, 3)})
    srgb = load_target(target, size=optics.roi)
    check_estimates([hologram_estimate(profile, len(select_channels(profile, colours)))], f"generate {target}")
    amplitude = prepare_target(srgb, slm.shape, optics.roi)
    scene = compute_scene(amplitude, bench, method, iterations=iterations, colours=colours, seed=seed,
                          progress=progress, checkpoint=checkpoint)
    out_dir = ensure_dir(Path(out_dir))  # only once there is something to write
    files = []
    for c in scene.colours:
        if c.gray is not None:  # a skipped colour has none
            files.append(write_png(out_dir / f"phase_{c.channel}.png", c.gray).name)
    files.append(write_png(out_dir / "target.png", _srgb8(scene.target_roi.square())).name)
    files.append(write_png(out_dir / "reconstruction.png", _srgb8(scene.merged_linear)).name)
    metrics = {
        "benchctl_version": benchctl.__version__,
        "benchctl_code": code_identity(),
        "target": target,
        "profile": str(profile.path),
        "grid": list(slm.shape),
        "roi": list(optics.roi),
        "optical_model": str(optics.model) if optics.model else None,
        "calibration": calibration_used(profile, own_tables),  # tables and model, with checksums
        "seed": seed,
        "started_unix": round(started, 3),
        **scene_metrics(scene),
        "files": files + ["metrics.json"],
    }
    write_json(out_dir / "metrics.json", metrics)
    return metrics


def depth_scene_metrics(scene: DepthSceneResult) -> dict[str, Any]:
    """The planes, per-plane and per-colour figures of a scene with depth, as plain JSON-ready values."""
    def rounded(scores: dict[str, float] | None) -> dict[str, float] | None:
        return None if scores is None else {k: round(v, 4) for k, v in scores.items()}

    colours: dict[str, dict[str, Any]] = {}
    for c in scene.colours:
        colours[c.channel] = {"wavelength_nm": c.wavelength_nm, "skipped": c.skipped}
        if not c.skipped:
            colours[c.channel] |= {"seconds": round(c.seconds, 4), "mean": rounded(c.scores),
                                   "planes": [rounded(p) for p in c.plane_scores]}
    return {
        "method": scene.method,
        "iterations": scene.iterations,
        "checkpoint": str(scene.checkpoint) if scene.checkpoint is not None else None,
        "planes": [{"distance_mm": round(z * 1e3, 4), "in_focus": round(share, 4), "scores": rounded(scores)}
                   for z, share, scores in zip(scene.planes.planes_m, scene.in_focus, scene.plane_scores)],
        "planes_reason": scene.planes.reason,
        "sweep_mm": None if scene.planes.sweep is None else [[round(z * 1e3, 4) for z in depths]
                                                             for depths in scene.planes.sweep.depths_m],
        "mean": rounded(scene.mean_scores),
        "seconds": round(sum(c.seconds for c in scene.colours), 4),
        "colours": colours,
    }


def _write_depth_scene(scene: DepthSceneResult, note: str | None, out_dir: Path,
                       record: dict[str, Any]) -> dict[str, Any]:
    """Write a scene with depth: each colour's hologram, the all-in-focus target, the depth (16-bit, 0 and 65535 at
    the scene's nearest and farthest depth), the focal stack (one image per plane) and metrics.json."""
    out_dir = ensure_dir(out_dir)
    files = [write_png(out_dir / f"phase_{c.channel}.png", c.gray).name for c in scene.colours if c.gray is not None]
    files.append(write_png(out_dir / "target.png", _srgb8(scene.target_roi.square())).name)
    near, far = float(scene.depth_roi.min()), float(scene.depth_roi.max())
    depth16 = ((scene.depth_roi - near) / max(far - near, 1e-12) * 65535).round().to(torch.int32).numpy()
    files.append(write_png(out_dir / "depth.png", depth16.astype(np.uint16)).name)
    for k, z in enumerate(scene.planes.planes_m):
        files.append(write_png(out_dir / f"plane_{k + 1:02d}_{z * 1e3:.2f}mm.png", _srgb8(scene.stack_linear[k])).name)
    metrics = {**record, "scene_note": note, "depth_png_mm": [round(near * 1e3, 4), round(far * 1e3, 4)],
               **depth_scene_metrics(scene), "files": files + ["metrics.json"]}
    write_json(out_dir / "metrics.json", metrics)
    return metrics
