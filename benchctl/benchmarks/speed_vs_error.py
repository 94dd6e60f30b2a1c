"""`benchctl bench speed-vs-error`: one speed-against-error front for every hologram method and iteration budget.

Every method runs in one process, side by side, on the bundled charts and the held-out photographs: DPAC, GS
and SGD at each budget, each learned method whose checkpoint fits the benchmark's geometry (one-shot), and
that network refined by SGD (`<name>+sgd`, at each budget). Learned methods without a fitting checkpoint are
skipped with the reason printed. The per-target table is followed by the front: one row per method and
budget, means over targets, and whether the row is on the Pareto front of time per frame against PSNR.

A scene with depth (`rgbd:...`) is run by the methods that make focal stacks, at the planes it needs
(`compute_depth_scene`), and scored by the amplitude PSNR of its all-in-focus image (each pixel where the hologram is
meant to be seen nearest its depth: a plane, or a depth of the plane's sweep) and the in-focus SSIM (mean over the
planes); run one scene at a time for its own front.
"""

from __future__ import annotations

import io
import math
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Callable

import torch

from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.geometry import grid_profile
from benchctl.calibration.setups import optical_setup
from benchctl.cgh import get_method, method_names
from benchctl.errors import BenchctlError
from benchctl.files import atomic_write_bytes, ensure_dir, write_csv
from benchctl.holograms.depth import compute_depth_scene, depth_scene_planes
from benchctl.holograms.scene import checkpoint_status, compute_scene, usable_methods
from benchctl.optics.metrics import pareto_front
from benchctl.profiles import Profile
from benchctl.scenes import is_scene, load_scene, prepare_scene
from benchctl.targets import load_target, photo_specs, prepare_target

CHART_TARGETS = ("chart:siemens", "chart:bars", "chart:text")
DEFAULT_TARGETS = (*CHART_TARGETS, *photo_specs("eval"))
DEFAULT_BUDGETS = (10, 50, 200, 500)
FULL_BUDGETS = (10, 50)
"""Budgets at the profile's full geometry, where one SGD iteration costs ~16x what it costs scaled."""

ProgressFactory = Callable[[str], Callable[[int, int], None]]


def resized_profile(profile: Profile, size: tuple[int, int]) -> Profile:
    """The bench scaled to an SLM grid of `size` (H, W): ROI scaled per axis, distance by the area ratio.

    Keeping the pitch and scaling the distance with the grid's area keeps the Fresnel number
    (N pitch)^2 / (lambda z), so the image's resolution relative to its size and the quality figures stay
    comparable with the full bench, while the time per frame shrinks with the grid. (Learned methods only
    run where a checkpoint was trained for exactly this geometry, e.g. at the profile's own grid.)
    """
    return grid_profile(profile, size, scale_distance=True)


def size_refusal(profile: Profile, scene: str) -> tuple[str, None]:
    """What a benchmark's memory refusal for `scene` (one with depth) names: the scene and the grid as --size, the
    knob that shrinks it (a benchmark chooses its own planes, so it offers no fixed ones)."""
    rows, cols = profile.section("slm").shape
    return f"{scene} at --size {rows}x{cols}", None


def budgets_for(method: str, budgets: Sequence[int]) -> list[int | None]:
    """One-shot methods (DPAC, trained networks) run once; iterative ones (refined networks too) at every budget."""
    return [None] if get_method(method).default_iterations is None else list(budgets)


def default_methods(profile: Profile, out: Callable[[str], None] = print) -> tuple[str, ...]:
    """Every registered method that runs on this benchmark's geometry (the classical ones, and those whose
    network has a checkpoint that fits it); for each one left out, a line saying why."""
    usable = usable_methods(profile)
    for name in method_names():
        if name not in usable:
            out(f"not running {name}: {checkpoint_status(name, profile)}")
    return tuple(usable)


def _mean(values: Sequence[float]) -> float:
    return sum(values) / len(values) if values else float("nan")


def front_rows(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per method and budget from the per-target rows: means over targets (charts and photographs also
    apart), and `front`: on the Pareto front of seconds per frame against mean amplitude PSNR."""
    groups: dict[tuple[str, Any], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row["method"], row["iterations"]), []).append(row)
    front = []
    for (method, iterations), group in groups.items():
        charts = [r["psnr_amplitude_db"] for r in group if r["target"].startswith("chart:")]
        photos = [r["psnr_amplitude_db"] for r in group if not r["target"].startswith(("chart:", "rgbd:"))]
        front.append({
            "method": method,
            "iterations": iterations,
            "iterations_run": _mean([r["iterations_run"] for r in group]) if iterations != "" else "",
            "seconds_per_frame": _mean([r["seconds_per_frame"] for r in group]),
            "x_propagation": _mean([r["seconds_per_frame"] / r["propagation_seconds"] for r in group]),
            "psnr_amplitude_db": _mean([r["psnr_amplitude_db"] for r in group]),
            "psnr_amplitude_charts_db": _mean(charts),
            "psnr_amplitude_photos_db": _mean(photos),
            "ssim_amplitude": _mean([r["ssim_amplitude"] for r in group]),
            "psnr_srgb_db": _mean([r["psnr_srgb_db"] for r in group]),
            "targets": len(group),
        })
    on_front = pareto_front([(r["seconds_per_frame"], r["psnr_amplitude_db"]) for r in front])
    for row, on in zip(front, on_front):
        row["front"] = on
    return front


Target = torch.Tensor | tuple[torch.Tensor, torch.Tensor]
"""A 2D target's amplitude (3, H, W), or a scene's amplitude and depth (H, W)."""


def _load_targets(targets: Sequence[str], profile: Profile, out: Callable[[str], None]) -> dict[str, Target]:
    """Each target as (3, H, W) amplitude on the grid (a scene with depth: and its depth map); one that cannot be
    loaded is skipped with the reason, and when none can, the first reason is the error."""
    grid, optics = profile.section("slm").shape, profile.section("optics")
    roi = optics.roi
    amplitudes: dict[str, Target] = {}
    errors = []
    for spec in targets:
        try:
            if is_scene(spec):
                amplitudes[spec] = prepare_scene(load_scene(spec, roi, optics.depth_range_m), grid, roi)
            else:
                amplitudes[spec] = prepare_target(load_target(spec, size=roi), grid, roi)
        except BenchctlError as error:
            out(f"not running target {spec}: {error}")
            errors.append(error)
    if not amplitudes:
        raise errors[0]
    return amplitudes


def _recording(progress: ProgressFactory | None, last: dict[str, int]) -> ProgressFactory:
    """A progress factory that remembers the last `done` per colour (the iterations an early stop ran)."""
    def factory(label: str) -> Callable[[int, int], None]:
        inner = progress(label) if progress is not None else None

        def report(done: int, total: int) -> None:
            last[label] = done
            if inner is not None:
                inner(done, total)
        return report
    return factory


def run_speed_vs_error(
    profile: Profile,
    *,
    targets: Sequence[str] = DEFAULT_TARGETS,
    methods: Sequence[str] | None = None,
    budgets: Sequence[int] = DEFAULT_BUDGETS,
    colours: list[str] | None = None,
    seed: int = 0,
    out_dir: Path | None = None,
    out: Callable[[str], None] = print,
    progress: ProgressFactory | None = None,
) -> list[dict[str, Any]]:
    """Run each method at each budget on each target; print the per-target table and the front, write CSVs
    (+ a PNG plot with matplotlib). Returns the front's rows (one per method and budget)."""
    methods = tuple(methods or default_methods(profile, out))
    for name in methods:
        get_method(name)  # an unknown name fails here, before any work, listing the known ones
    amplitudes = _load_targets(targets, profile, out)
    slm, optics = profile.section("slm"), profile.section("optics")
    grid, roi = slm.shape, optics.roi
    unit = _propagation_seconds(profile, colours[0] if colours else profile.channels[0].name)
    bench = Calibrated(profile)  # the profile as configured: nothing measured applies to a scaled grid
    for spec, amplitude in amplitudes.items():  # every scene's memory checked before any target is computed
        if isinstance(amplitude, tuple):
            depth_scene_planes(*amplitude, bench, colours=colours, refusal=size_refusal(profile, spec))
    # Warm-up, outside the timed frames: every colour's transfer functions, and each method's first call (the first
    # Adam step alone took 8 s: lazy imports), once on each kind of target.
    for first in {isinstance(a, tuple): a for a in amplitudes.values()}.values():
        for method in dict.fromkeys(("dpac", *methods)):
            if isinstance(first, tuple) and get_method(method).focal_stack is None:
                continue
            shortest = budgets_for(method, (1,))[0]
            if isinstance(first, tuple):
                compute_depth_scene(*first, bench, method, iterations=shortest, colours=colours, perceptual=False)
            else:
                compute_scene(first, bench, method, iterations=shortest, colours=colours)
    out(f"grid {grid[0]}x{grid[1]}, ROI {roi[0]}x{roi[1]}, distance {optics.distance_mm:g} mm, "
        f"pitch {slm.pitch_um:g} um, targets: {', '.join(amplitudes)}")
    out(f"one propagation ({colours[0] if colours else profile.channels[0].name}, measured in this run): "
        f"{unit * 1e3:.2f} ms; "
        "'x prop' = seconds per frame / that")
    out(f"{'method':<18} {'iters':>6} {'run':>6} {'target':<16} {'s/frame':>9} {'x prop':>8} {'PSNR amp':>9} "
        f"{'SSIM amp':>9} {'PSNR sRGB':>10} {'SSIM sRGB':>10}")
    rows = []
    for method in methods:
        for iterations in budgets_for(method, budgets):
            for target, amplitude in amplitudes.items():
                last: dict[str, int] = {}
                if isinstance(amplitude, tuple) and get_method(method).focal_stack is None:
                    out(f"not running {method} on {target}: it makes holograms of one plane")
                    continue
                if isinstance(amplitude, tuple):  # all-in-focus PSNR, SSIM over the planes; no merged sRGB image
                    stack = compute_depth_scene(*amplitude, bench, method, iterations=iterations, colours=colours,
                                                seed=seed, progress=_recording(progress, last), perceptual=False)
                    done = [c for c in stack.colours if not c.skipped]
                    planes, srgb = len(stack.planes.planes_m), {"psnr_srgb_db": math.nan, "ssim_srgb": math.nan}
                    psnr_key = "all_in_focus_psnr_db"
                else:
                    scene = compute_scene(amplitude, bench, method, iterations=iterations, colours=colours,
                                          seed=seed, progress=_recording(progress, last))
                    done = [c for c in scene.colours if not c.skipped]
                    planes, srgb = 1, {key: scene.merged_scores[key] for key in ("psnr_srgb_db", "ssim_srgb")}
                    psnr_key = "psnr_amplitude_db"
                row: dict[str, Any] = {  # a CSV row: numbers, and "" where a method has no budget
                    "method": method,
                    "iterations": iterations if iterations is not None else "",
                    "iterations_run": _mean(list(last.values())) if iterations is not None else "",
                    "target": target,
                    "planes": planes,
                    "frames": len(done),
                    "seconds_per_frame": _mean([c.seconds for c in done]),
                    "propagation_seconds": unit,
                    "psnr_amplitude_db": _mean([c.scores[psnr_key] for c in done]),
                    "ssim_amplitude": _mean([c.scores["ssim_amplitude"] for c in done]),
                    **srgb,
                }
                rows.append(row)
                run = f"{row['iterations_run']:.0f}" if iterations is not None else ""
                out(f"{method:<18} {row['iterations']!s:>6} {run:>6} {target:<16} {row['seconds_per_frame']:>9.3f} "
                    f"{row['seconds_per_frame'] / unit:>8.1f} {row['psnr_amplitude_db']:>9.2f} "
                    f"{row['ssim_amplitude']:>9.3f} {row['psnr_srgb_db']:>10.2f} {row['ssim_srgb']:>10.3f}")
    front = front_rows(rows)
    out("")
    out("front: means over targets; amplitude PSNR on the ROI; * = on the Pareto front (time against PSNR amp)")
    out(f"{'method':<18} {'iters':>6} {'run':>6} {'s/frame':>9} {'x prop':>8} {'PSNR amp':>9} {'charts':>7} "
        f"{'photos':>7} {'SSIM amp':>9} {'PSNR sRGB':>10} front")
    for row in front:
        run = f"{row['iterations_run']:.0f}" if row["iterations"] != "" else ""
        out(f"{row['method']:<18} {row['iterations']!s:>6} {run:>6} {row['seconds_per_frame']:>9.3f} "
            f"{row['x_propagation']:>8.1f} {row['psnr_amplitude_db']:>9.2f} {row['psnr_amplitude_charts_db']:>7.2f} "
            f"{row['psnr_amplitude_photos_db']:>7.2f} {row['ssim_amplitude']:>9.3f} {row['psnr_srgb_db']:>10.2f} "
            f"{'*' if row['front'] else ''}")
    if out_dir is not None:
        out_dir = ensure_dir(Path(out_dir))
        out(f"wrote {write_csv(out_dir / 'speed_vs_error.csv', rows)}")
        out(f"wrote {write_csv(out_dir / 'front.csv', front)}")
        plot = _plot(front, out_dir / "speed_vs_error.png", f"grid {grid[0]}x{grid[1]}")
        out(f"wrote {plot}" if plot else "no plot: install the 'plot' extra (matplotlib) for speed_vs_error.png")
    return front


def _propagation_seconds(profile: Profile, channel: str, repeats: int = 5) -> float:
    """Median time of one SLM -> target propagation of a random phase on this grid (after a warm-up)."""
    setup = optical_setup(profile, channel)
    generator = torch.Generator().manual_seed(0)
    field = torch.polar(torch.ones(setup.shape), torch.rand(setup.shape, generator=generator) * 6.283)
    propagate = setup.target_propagator()
    propagate(field)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        propagate(field)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


_MARKERS = "osD^v<>phX*P"


def _plot(front: list[dict[str, Any]], path: Path, title: str) -> Path | None:
    """Seconds per frame (log) against mean amplitude PSNR: one marker per method, budgets annotated, the
    Pareto front as a step line; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig, ax = plt.subplots(figsize=(8, 5))
    for index, method in enumerate(dict.fromkeys(r["method"] for r in front)):
        points = [r for r in front if r["method"] == method]
        ax.plot([r["seconds_per_frame"] for r in points], [r["psnr_amplitude_db"] for r in points],
                marker=_MARKERS[index % len(_MARKERS)], linestyle=":", label=method)
        for r in points:
            if r["iterations"] != "":
                ax.annotate(str(r["iterations"]), (r["seconds_per_frame"], r["psnr_amplitude_db"]),
                            textcoords="offset points", xytext=(4, 4), fontsize=7)
    best = sorted((r for r in front if r["front"]), key=lambda r: r["seconds_per_frame"])
    ax.step([r["seconds_per_frame"] for r in best], [r["psnr_amplitude_db"] for r in best], where="post",
            color="black", linewidth=1.5, alpha=0.6, label="Pareto front")
    ax.set_xscale("log")
    ax.set_xlabel("seconds per frame (one colour)")
    ax.set_ylabel("PSNR, amplitude on the ROI (dB), mean over targets")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=120)
    plt.close(fig)
    return atomic_write_bytes(path, buffer.getvalue())
