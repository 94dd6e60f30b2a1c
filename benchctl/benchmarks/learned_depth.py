"""`benchctl bench learned-depth`: trained networks for scenes with depth against classical holograms, on held-out
scenes: focal-stack quality per plane, and time.

On the bench the checkpoints were trained for (their recorded geometry and depth range, which must agree), per
held-out scene (the bundled `rgbd:` scenes, never drawn by the training data) and one colour:
- the scene prepared as `benchctl generate` prepares it (`scenes.load_scene`, `scenes.prepare_scene`), its focal
  planes by `training.data.loss_planes` (a layered scene's own depths, else `planes` evenly over its depth span,
  bin centres, no jitter) and its in-focus masks;
- each checkpoint's network: one forward pass on the image and its depth;
- layered DPAC (the registry's `dpac` of a scene with depth: the scene's field layer by layer with occlusion,
  anti-aliased, double-phase coded; one shot);
- multi-plane SGD (the registry's SGD of a scene with depth: Adam on the SLM phase minimising the focal-stack loss,
  Neural 3D Holography's masked loss, from layered DPAC) for exactly `sgd_iterations` (no early stop, so every
  scene gets the same budget); the best phase seen is kept;
all scored by `focal_stack_scores` (each plane's amplitude PSNR / SSIM inside its in-focus region, unquantised
phase, and the mean over the planes) and timed (wall seconds per hologram on this machine, after a warm-up that
computes the propagation kernels and runs one SGD iteration). Several
checkpoints of one method (seeds) give a mean and a standard deviation over the seeds.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from benchctl.cgh import OpticalSetup
from benchctl.cgh.dpac import DPAC
from benchctl.cgh.learned import DEPTH_METHODS, DepthHologramNet
from benchctl.cgh.sgd import DEFAULT_ITERATIONS, sgd_method
from benchctl.errors import BadValueError
from benchctl.files import ensure_dir, write_csv
from benchctl.holograms.checkpoints import read_checkpoint
from benchctl.optics.focal_stack import FocalStackTarget
from benchctl.profiles import Profile
from benchctl.scenes import list_scenes, load_scene, prepare_scene
from benchctl.targets import target_plane
from benchctl.training.data import loss_planes
from benchctl.training.training import peak_normalised, phase_stack_scores

DPAC_LABEL = "layered dpac"
SGD_LABEL = "multi-plane sgd"


@dataclass
class Network:
    """One checkpoint's network for the bench: its method, training seed and model."""

    method: str
    seed: int
    model: DepthHologramNet
    path: Path


def _networks(paths: Sequence[Path], colour: str | None) -> tuple[list[Network], OpticalSetup, str]:
    """The checkpoints' models for one colour, checked to share one geometry and one depth range."""
    if not paths:
        raise BadValueError("give the trained checkpoints of holonet3d networks with --checkpoint")
    networks: list[Network] = []
    first: tuple[dict[str, Any], tuple[float, float]] | None = None
    for path in paths:
        checkpoint = read_checkpoint(path)
        if checkpoint.method not in DEPTH_METHODS:
            raise BadValueError(f"--checkpoint {path} holds {checkpoint.method}, not a network for scenes with depth "
                                f"({', '.join(DEPTH_METHODS)})")
        chosen = colour or checkpoint.colours[0]
        if chosen not in checkpoint.colours:
            raise BadValueError(f"--checkpoint {path} has no {chosen} model (it has {', '.join(checkpoint.colours)})")
        model = checkpoint.model(chosen)
        assert isinstance(model, DepthHologramNet)
        here = (checkpoint.geometry[chosen].to_dict(), model.depth_range_m)
        if first is None:
            first, colour = here, chosen
        elif here != first:
            raise BadValueError(f"--checkpoint {path} was trained for another bench or depth range than "
                                f"{paths[0]}: compare them on one bench")
        networks.append(Network(checkpoint.method, int(checkpoint.training.get("seed", 0)), model, Path(path)))
    assert colour is not None
    return networks, networks[0].model.setup, colour


def run_learned_depth_bench(profile: Profile, checkpoints: Sequence[Path], *, scenes: Sequence[str] | None = None,
                            colour: str | None = None, planes: int = 5, sgd_iterations: int = DEFAULT_ITERATIONS,
                            out_dir: Path | None = None, out: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Score each checkpoint's network, layered DPAC and multi-plane SGD on held-out scenes (module doc); print the
    table, write learned_depth.csv (one row per scene, method, seed and plane) and learned_depth_summary.csv."""
    networks, setup, colour = _networks(checkpoints, colour)
    depth_range = networks[0].model.depth_range_m
    specs = list(scenes or list_scenes())
    plane = target_plane(profile.channel(colour))
    sgd = sgd_method(SGD_LABEL, tolerance=None)
    out(f"bench of the checkpoints: {setup.shape[0]}x{setup.shape[1]} (ROI {setup.roi[0]}x{setup.roi[1]}), {colour} "
        f"{setup.wavelength_m * 1e9:g} nm, distance {setup.distance_m * 1e3:.4g} mm, depth range "
        f"{depth_range[0] * 1e3:.4g} .. {depth_range[1] * 1e3:.4g} mm; up to {planes} planes per scene; multi-plane "
        f"SGD {sgd_iterations} iterations from layered DPAC; unquantised phase; {torch.get_num_threads()} "
        "torch thread(s)")
    rows: list[dict[str, Any]] = []
    for spec in specs:
        scene = load_scene(spec, setup.roi, depth_range)
        amplitudes, depth = prepare_scene(scene, setup.shape, setup.roi)
        amplitude = peak_normalised(amplitudes[plane][None, None])[0, 0]
        roi_rows, roi_cols = setup.roi_slices
        focal = loss_planes(depth[roi_rows, roi_cols].numpy(), planes)
        target = FocalStackTarget(amplitude, depth, focal)
        # untimed warm-up: every propagation kernel this scene needs is computed once, as for repeated holograms,
        # and one SGD iteration (a process's first Adam step takes seconds of lazy imports)
        DPAC(target, setup)
        sgd(target, setup, iterations=1)
        with torch.inference_mode():
            networks[0].model(amplitude[None, None], depth[None, None])
        results: list[tuple[str, int | None, torch.Tensor, float]] = []
        start = time.perf_counter()
        results.append((DPAC_LABEL, None, DPAC(target, setup), time.perf_counter() - start))
        start = time.perf_counter()
        results.append((SGD_LABEL, None, sgd(target, setup, iterations=sgd_iterations),
                        time.perf_counter() - start))  # its layered DPAC start included
        for network in networks:
            start = time.perf_counter()
            with torch.inference_mode():
                phase = network.model(amplitude[None, None], depth[None, None])[0, 0].clone()
            results.append((network.method, network.seed, phase, time.perf_counter() - start))
        for label, seed, phase, seconds in results:
            scored = phase_stack_scores(phase, setup, amplitude, depth, focal)[1]
            mean = scored.mean
            for k, (z, scores) in enumerate(zip(focal, scored.per_plane)):
                rows.append({"scene": spec, "method": label, "seed": "" if seed is None else seed, "plane": k,
                             "plane_mm": round(z * 1e3, 5), "seconds": round(seconds, 4),
                             "psnr_amplitude_db": None if scores is None else round(scores["psnr_amplitude_db"], 3),
                             "ssim_amplitude": None if scores is None else round(scores["ssim_amplitude"], 4),
                             "mean_psnr_amplitude_db": round(mean["psnr_amplitude_db"], 3),
                             "mean_ssim_amplitude": round(mean["ssim_amplitude"], 4)})
        out(f"  {spec}: {len(focal)} plane(s) at {', '.join(f'{z * 1e3:.4g}' for z in focal)} mm")
    summary = summarise(rows)
    for line in format_summary(summary):
        out(line)
    if out_dir is not None:
        folder = ensure_dir(Path(out_dir))
        out(f"wrote {write_csv(folder / 'learned_depth.csv', rows)} and "
            f"{write_csv(folder / 'learned_depth_summary.csv', summary)}")
    return rows


def summarise(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per scene (and over all scenes) and method: the mean in-focus PSNR / SSIM, each plane's PSNR and the seconds,
    as the mean and the standard deviation over the method's seeds."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    summary = []
    for scene in [*scenes, "all scenes"]:
        for method in methods:
            mine = [r for r in rows if r["method"] == method and scene in (r["scene"], "all scenes")]
            seeds = list(dict.fromkeys(r["seed"] for r in mine))
            row: dict[str, Any] = {"scene": scene, "method": method, "seeds": len(seeds)}
            for key in ("mean_psnr_amplitude_db", "mean_ssim_amplitude", "seconds"):
                # per seed, the mean over its scenes (a scene's rows, one per plane, repeat its value)
                values = [statistics.mean({r["scene"]: r[key] for r in mine if r["seed"] == seed}.values())
                          for seed in seeds]
                row[key] = statistics.mean(values)
                row[f"{key}_std"] = statistics.stdev(values) if len(values) > 1 else 0.0
            if scene != "all scenes":
                per_plane = [[r["psnr_amplitude_db"] for r in mine if r["plane"] == k]
                             for k in sorted({r["plane"] for r in mine})]
                row["plane_psnr_db"] = " / ".join(
                    "-" if None in values else f"{statistics.mean(values):.2f}" for values in per_plane)
            summary.append(row)
    return summary


def format_summary(summary: Sequence[dict[str, Any]]) -> list[str]:
    """The printed table: one line per scene and method, mean +- standard deviation over seeds."""
    lines = [f"{'scene':<18} {'method':<20} {'seeds':>5} {'PSNR dB (in focus)':>19} {'SSIM':>14} {'s/hologram':>11}  "
             "PSNR per plane (near -> far)"]
    for r in summary:
        lines.append(f"{r['scene']:<18} {r['method']:<20} {r['seeds']:>5} "
                     f"{r['mean_psnr_amplitude_db']:>10.2f} +- {r['mean_psnr_amplitude_db_std']:<5.2f} "
                     f"{r['mean_ssim_amplitude']:>6.3f} +- {r['mean_ssim_amplitude_std']:<5.3f} {r['seconds']:>11.3f}  "
                     f"{r.get('plane_psnr_db', '')}")
    return lines
