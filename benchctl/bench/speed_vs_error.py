"""`benchctl bench speed-vs-error`: seconds per frame against PSNR / SSIM for every method and iteration budget.

Learned methods take part where a trained checkpoint fits the benchmark's geometry (shipped for the profile,
see `benchctl.cgh.learned.find_checkpoint`); they are one-shot, like DPAC.
"""

from __future__ import annotations

import io
import statistics
import time
from pathlib import Path
from typing import Any, Callable

import torch

from benchctl.cgh import OpticalSetup, get_method, method_names
from benchctl.cgh.learned import LEARNED_METHODS, find_checkpoint, read_checkpoint
from benchctl.cgh.learned.geometry import grid_profile
from benchctl.files import atomic_write_bytes, ensure_dir, write_csv
from benchctl.profiles import Profile
from benchctl.runner.holograms import checkpoint_status, compute_scene, usable_learned_methods
from benchctl.targets import load_target, prepare_target

DEFAULT_TARGETS = ("chart:siemens", "chart:bars", "chart:text")
DEFAULT_BUDGETS = (10, 50, 200, 500)


def resized_profile(profile: Profile, size: tuple[int, int]) -> Profile:
    """The bench scaled to an SLM grid of `size` (H, W): ROI scaled per axis, distance by the area ratio.

    Keeping the pitch and scaling the distance with the grid's area keeps the Fresnel number
    (N pitch)^2 / (lambda z), so the image's resolution relative to its size and the quality figures stay
    comparable with the full bench, while the time per frame shrinks with the grid. (Learned methods only
    run where a checkpoint was trained for exactly this geometry, e.g. at the profile's own grid.)
    """
    return grid_profile(profile, size, scale_distance=True)


def budgets_for(method: str, budgets: tuple[int, ...]) -> list[int | None]:
    """One-shot methods (DPAC, trained networks) run once; iterative ones run at every budget."""
    if method in LEARNED_METHODS:
        return [None]
    return [None] if get_method(method).default_iterations is None else list(budgets)


def default_methods(profile: Profile, out: Callable[[str], None] = print) -> tuple[str, ...]:
    """Every classical method, plus each learned method with a checkpoint that fits this benchmark's geometry
    (and a note for those whose checkpoint is for another geometry)."""
    learned = usable_learned_methods(profile)
    for name in LEARNED_METHODS:
        path = find_checkpoint(name, profile)
        if path is not None and name not in learned:
            grid = next(iter(read_checkpoint(path).geometry.values()))["grid"]
            out(f"not running {name}: {checkpoint_status(name, profile)} (--size {grid[0]}x{grid[1]} includes it "
                "when the rest of the geometry is the profile's)")
    return (*method_names(), *learned)


def run_speed_vs_error(
    profile: Profile,
    *,
    targets: tuple[str, ...] = DEFAULT_TARGETS,
    methods: tuple[str, ...] | None = None,
    budgets: tuple[int, ...] = DEFAULT_BUDGETS,
    seed: int = 0,
    out_dir: Path | None = None,
    out: Callable[[str], None] = print,
    progress: Callable[[str], Callable[[int, int], None]] | None = None,
) -> list[dict[str, Any]]:
    """Run each method at each budget on each target; print a table, write CSV (+ PNG plot if matplotlib)."""
    methods = tuple(methods or default_methods(profile, out))
    for name in methods:
        if name not in LEARNED_METHODS:
            get_method(name)
    grid, roi = profile.slm.shape, profile.optics.roi
    amplitudes = {t: prepare_target(load_target(t, size=roi), grid, roi) for t in targets}
    unit = _propagation_seconds(profile)
    out(f"grid {grid[0]}x{grid[1]}, ROI {roi[0]}x{roi[1]}, distance {profile.optics.distance_mm:g} mm, "
        f"pitch {profile.slm.pitch_um:g} um, targets: {', '.join(targets)}")
    out(f"one propagation ({profile.channels[0].name}, measured in this run): {unit * 1e3:.2f} ms; "
        "'x prop' = seconds per frame / that")
    header = (f"{'method':<14} {'iters':>6} {'target':<16} {'s/frame':>9} {'x prop':>8} {'PSNR amp':>9} "
              f"{'SSIM amp':>9} {'PSNR sRGB':>10} {'SSIM sRGB':>10}")
    out(header)
    rows = []
    for method in methods:
        for iterations in budgets_for(method, budgets):
            for target, amplitude in amplitudes.items():
                scene = compute_scene(amplitude, profile, method, iterations=iterations, seed=seed, progress=progress)
                done = [c for c in scene.colours if not c.skipped]
                row = {
                    "method": method,
                    "iterations": iterations if iterations is not None else "",
                    "target": target,
                    "frames": len(done),
                    "seconds_per_frame": sum(c.seconds for c in done) / max(len(done), 1),
                    "propagation_seconds": unit,
                    "psnr_amplitude_db": sum(c.scores["psnr_amplitude_db"] for c in done) / max(len(done), 1),
                    "ssim_amplitude": sum(c.scores["ssim_amplitude"] for c in done) / max(len(done), 1),
                    "psnr_srgb_db": scene.merged_scores["psnr_srgb_db"],
                    "ssim_srgb": scene.merged_scores["ssim_srgb"],
                }
                rows.append(row)
                out(f"{method:<14} {row['iterations']!s:>6} {target:<16} {row['seconds_per_frame']:>9.3f} "
                    f"{row['seconds_per_frame'] / unit:>8.1f} "
                    f"{row['psnr_amplitude_db']:>9.2f} {row['ssim_amplitude']:>9.3f} {row['psnr_srgb_db']:>10.2f} "
                    f"{row['ssim_srgb']:>10.3f}")
    if out_dir is not None:
        out_dir = ensure_dir(Path(out_dir))
        out(f"wrote {write_csv(out_dir / 'speed_vs_error.csv', rows)}")
        plot = _plot(rows, out_dir / "speed_vs_error.png")
        out(f"wrote {plot}" if plot else "no plot: install the 'plot' extra (matplotlib) for speed_vs_error.png")
    return rows


def _propagation_seconds(profile: Profile, repeats: int = 5) -> float:
    """Median time of one SLM -> target propagation of a random phase on this grid (after a warm-up)."""
    setup = OpticalSetup.from_profile(profile, profile.channels[0].name)
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


def _plot(rows: list[dict[str, Any]], path: Path) -> Path | None:
    """Seconds per frame (log) against merged sRGB PSNR, one line per method; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for method in dict.fromkeys(r["method"] for r in rows):
        points: dict[Any, list[dict[str, Any]]] = {}
        for r in rows:
            if r["method"] == method:
                points.setdefault(r["iterations"], []).append(r)
        xs = [sum(r["seconds_per_frame"] for r in rs) / len(rs) for rs in points.values()]
        ys = [sum(r["psnr_srgb_db"] for r in rs) / len(rs) for rs in points.values()]
        ax.plot(xs, ys, marker="o", label=method)
        for x, y, iters in zip(xs, ys, points):
            if iters != "":
                ax.annotate(str(iters), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("seconds per frame (one colour)")
    ax.set_ylabel("merged PSNR, sRGB (dB), mean over targets")
    ax.grid(True, alpha=0.3)
    ax.legend()
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=120)
    plt.close(fig)
    return atomic_write_bytes(path, buffer.getvalue())
