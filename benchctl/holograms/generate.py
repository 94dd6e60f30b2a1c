"""`benchctl generate`: holograms for a target, written exactly as displayed, with reconstruction and metrics."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

import benchctl
from benchctl.calibration.files import calibration_used
from benchctl.calibration.store import Calibration
from benchctl.cgh import DEFAULT_METHOD
from benchctl.files import ensure_dir, write_json
from benchctl.holograms.scene import SceneResult, compute_scene
from benchctl.images import write_png
from benchctl.optics import linear_to_srgb
from benchctl.profiles import Profile
from benchctl.provenance import code_identity
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
) -> dict[str, Any]:
    """Generate one hologram per colour present in `target`, write PNGs and metrics.json to `out_dir`.

    A learned method uses `checkpoint`, else the one shipped for the profile (see `compute_scene`). What
    calibration/<profile>/ holds is used as a run uses it: the measured lookup tables (for the channels whose
    table the profile does not name) and the fitted optical model.
    """
    started = time.time()
    profile.require("slm", "optics", "laser")  # the laser's channels are the colours generated
    own_tables = profile.section("slm").lut
    profile = Calibration.store(profile).applied(profile)
    slm, optics = profile.section("slm"), profile.section("optics")
    srgb = load_target(target, size=optics.roi)
    amplitude = prepare_target(srgb, slm.shape, optics.roi)
    scene = compute_scene(amplitude, profile, method, iterations=iterations, colours=colours, seed=seed,
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
