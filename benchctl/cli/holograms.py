"""`benchctl generate | models | targets`: holograms for a target, the methods and targets there are."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from benchctl.cli.args import EPILOG, add_profile, count, grid_size, name_list, plane_count, print_lines


def _cmd_generate(args: argparse.Namespace) -> int:
    from benchctl.calibration.files import calibration_lines
    from benchctl.cgh import DEFAULT_METHOD, get_method
    from benchctl.errors import BadValueError
    from benchctl.holograms.generate import run_generate
    from benchctl.scenes import is_scene
    from benchctl.profiles import load_profile
    from benchctl.terminal import ProgressLine

    profile = load_profile(args.profile)
    method = args.method or DEFAULT_METHOD
    if not is_scene(args.target) and (args.planes is not None or args.fit_depth):
        raise BadValueError(f"--planes and --fit-depth are for scenes with depth (rgbd:...), not {args.target}")
    planes = args.planes if isinstance(args.planes, int) else None  # None: auto
    if args.iterations == 0 and get_method(method).default_iterations is not None:
        print(f"{method}: --iterations 0 runs no iteration: the holograms are {method}'s starting phase alone")
    metrics = run_generate(args.target, profile, Path(args.out), method=method, iterations=args.iterations,
                           colours=args.colours, seed=args.seed, progress=ProgressLine, checkpoint=args.checkpoint,
                           planes=planes, fit_depth=args.fit_depth)
    if metrics["checkpoint"]:
        print(f"{method}: trained models from {metrics['checkpoint']}")
    for line in calibration_lines(metrics["calibration"]):
        print(line)
    if "planes" in metrics:
        return print_lines(focal_stack_lines(metrics) + [f"wrote {args.out}/"])
    for name, colour in metrics["colours"].items():
        if colour["skipped"]:
            print(f"{name:>6}: skipped (black in the target)")
        else:
            print(f"{name:>6}: {colour['seconds']:.2f} s, PSNR {colour['psnr_amplitude_db']:.2f} dB amplitude, "
                  f"SSIM {colour['ssim_amplitude']:.3f}")
    merged = metrics["merged"]
    print(f"merged: PSNR {merged['psnr_srgb_db']:.2f} dB sRGB, SSIM {merged['ssim_srgb']:.3f}; wrote {args.out}/")
    return 0


def focal_stack_lines(metrics: dict[str, Any]) -> list[str]:
    """A scene with depth as `generate` prints it: the note and the planes' reason, a table of the planes (share in
    focus, amplitude PSNR / SSIM, FLIP, speckle contrast: means over the colours), the mean and each colour's time."""
    def cell(scores: dict[str, float] | None, key: str, spec: str) -> str:
        return format(scores[key], spec) if scores and key in scores else "-"

    lines = [metrics["scene_note"]] if metrics.get("scene_note") else []
    lines.append(f"planes: {metrics['planes_reason']}")
    lines.append(f"{'plane':>5} {'mm':>8} {'in focus':>9} {'PSNR dB':>8} {'SSIM':>6} {'FLIP':>6} {'speckle':>8}")
    for k, plane in enumerate(metrics["planes"], start=1):
        scores = plane["scores"]
        lines.append(f"{k:>5} {plane['distance_mm']:>8.2f} {plane['in_focus']:>9.1%} "
                     f"{cell(scores, 'psnr_amplitude_db', '.2f'):>8} {cell(scores, 'ssim_amplitude', '.3f'):>6} "
                     f"{cell(scores, 'flip', '.3f'):>6} {cell(scores, 'speckle_contrast', '.3f'):>8}")
    mean = metrics["mean"]
    lines.append(f"{'mean':>5} {'':>8} {'':>9} {cell(mean, 'psnr_amplitude_db', '.2f'):>8} "
                 f"{cell(mean, 'ssim_amplitude', '.3f'):>6} {cell(mean, 'flip', '.3f'):>6} "
                 f"{cell(mean, 'speckle_contrast', '.3f'):>8}")
    if mean and "all_in_focus_psnr_db" in mean:
        lines.append(f"all in focus: PSNR {mean['all_in_focus_psnr_db']:.2f} dB (each pixel seen at the depth nearest "
                     "its own of " + ("the sweep's" if metrics.get("sweep_mm") else "the planes'") + ")")
    colours = metrics["colours"].items()
    times = [f"{name} {colour['seconds']:.2f} s" for name, colour in colours if not colour["skipped"]]
    skipped = [name for name, colour in colours if colour["skipped"]]
    lines.append(f"time: {', '.join(times) or 'none'} ({metrics['seconds']:.2f} s)"
                 + (f"; skipped (black in the target): {', '.join(skipped)}" if skipped else ""))
    return lines


def _cmd_models(args: argparse.Namespace) -> int:
    from benchctl.calibration.calibrated import Calibrated
    from benchctl.holograms.scene import list_methods
    from benchctl.profiles import load_profile

    profile = load_profile(args.profile)
    shape = args.size or profile.section("slm").shape
    if profile.optics is not None:  # the lookup tables and optical model a checkpoint would meet here
        profile = Calibrated.stored(profile).profile
    print(f"hologram methods at {shape[0]}x{shape[1]} (checkpoints for profile {profile.name!r}):")
    return print_lines(list_methods(shape, profile))


def _cmd_targets(args: argparse.Namespace) -> int:
    from benchctl.scenes import list_scenes
    from benchctl.targets import list_targets

    for name, description in (list_targets() | list_scenes()).items():
        print(f"{name:<18} {description}")
    print(f"{'rgbd:FILE.toml':<18} your own scene with depth: image, depth (16-bit PNG or .npy in mm), near_mm, far_mm")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add this group's sub-commands to the `benchctl` sub-parsers (importing nothing heavy)."""
    gen = sub.add_parser("generate", help="phase holograms for a target, with simulated reconstruction and scores",
                         description="Generate one 8-bit phase PNG per colour (as the SLM displays it), the "
                                     "simulated reconstruction and metrics.json. Colours that are black in the "
                                     "target are skipped.", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    gen.add_argument("target", help="chart or photo name (e.g. chart:siemens, photo:coffee), image file, or a scene "
                                    "with depth: rgbd:<name> (e.g. rgbd:two-planes) or rgbd:<scene file>.toml "
                                    "(`benchctl targets` lists them)")
    gen.add_argument("--planes", type=plane_count, default=None, metavar="auto|K",
                     help="a scene with depth: 'auto' (default) for the planes its depth content and the bench's "
                          "depth of field need (one for a flat scene, said why; with continuous depth each plane is "
                          "swept through its share of the depth while an optimiser runs), or K fixed planes evenly "
                          "over its depth")
    gen.add_argument("--fit-depth", action="store_true",
                     help="a scene file whose depth lies outside the profile's optics.depth_range_mm: map its near .. "
                          "far onto that range (default: refuse)")
    gen.add_argument("--method", "-m",
                     help="hologram method (default: dpac, as in procedures; `benchctl models` lists them all); "
                          "learned ones, alone or refined as <learned>+sgd, need a trained checkpoint")
    gen.add_argument("--checkpoint", type=Path, metavar="CKPT",
                     help="trained models for a learned method (default: the one shipped for the profile)")
    gen.add_argument("--iterations", "-n", type=count, help="iterations for iterative methods (default: the "
                                                           "method's own; 0: the method's start alone)")
    gen.add_argument("--colours", "--colors", type=name_list, metavar="LIST",
                     help="comma-separated laser channels, e.g. red,green (default: all in the profile)")
    gen.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    gen.add_argument("--out", "-o", required=True, metavar="OUTDIR", help="folder for the PNGs and metrics.json")
    add_profile(gen)
    gen.set_defaults(func=_cmd_generate)

    models = sub.add_parser("models", help="hologram methods with family and parameter count at a grid size",
                            description="Every hologram method, its family and trainable parameters, and for a learned "
                                        "one the checkpoint it would use here, with what its record says: below DPAC "
                                        "on its validation images, trained without the lookup tables or the fitted "
                                        "optical model this profile's bench now has.")
    models.add_argument("--size", type=grid_size, metavar="HxW", help="grid (default: the profile's SLM)")
    add_profile(models)
    models.set_defaults(func=_cmd_models)

    targets = sub.add_parser("targets", help="list the bundled targets")
    targets.set_defaults(func=_cmd_targets)
