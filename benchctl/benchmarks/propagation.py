"""`benchctl bench propagation`: time and error of each padding mode, side by side with a bare FFT pair.

For every grid size x colour x padding mode it prints the plan, the time of one complex64 propagation, its
ratio to a bare `fft2` + `ifft2` of the same padded grid timed in the same run, and the relative L2 error on
the centred ROI against a converged float64 propagation. Each colour is a profile's channel on that grid
(`grid_profile`: pitch and distance kept, ROI scaled; the iris left out, which is not what padding is about).
The field is what a phase SLM shows: unit amplitude, uniformly random phase (seeded). Mode "auto+roi" is "auto"
computing only the ROI.

`run_multiplane_bench` times one field propagated to K planes (`MultiPlanePropagator`: one forward FFT, K inverse
ones) against K independent propagations of the same field, side by side, with each one's error against
independent float64 propagations.
"""

from __future__ import annotations

import math
import statistics
import time
from typing import Any, Callable, Sequence

import torch

from benchctl.calibration.geometry import grid_profile
from benchctl.optics.geometry import Geometry
from benchctl.optics.metrics import centred_slices
from benchctl.optics.multiplane import MultiPlanePropagator
from benchctl.optics.propagation import Padding, Propagator
from benchctl.profiles import Profile

PAPER_SIZES = ((1088, 1920), (2160, 3840))
ROI_MODE = "auto+roi"
""""auto" computing only the ROI on the smaller grid it needs (`window_plan`): what SGD, training and the
simulated scores use, since they look at nothing else."""


def _timer(device: torch.device) -> Callable[..., float]:
    """Seconds one call of `fn(*args)` takes, with the device synchronised around it."""
    def timed(fn: Callable[..., Any], *args: Any) -> float:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start = time.perf_counter()
        fn(*args)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return time.perf_counter() - start
    return timed


def _fft_pair(x: torch.Tensor) -> torch.Tensor:
    return torch.fft.ifft2(torch.fft.fft2(x))


def _relative_l2(estimate: torch.Tensor, reference: torch.Tensor) -> float:
    return float(torch.linalg.vector_norm(estimate.to(reference.dtype) - reference)
                 / torch.linalg.vector_norm(reference))


def run_propagation_bench(
    profile: Profile,
    sizes: Sequence[tuple[int, int]] = PAPER_SIZES,
    *,
    modes: Sequence[Padding] = ("none", "2x", "auto", ROI_MODE),
    repeats: int = 5,
    reference_factor: int = 4,
    seed: int = 0,
    device: str | torch.device = "cpu",
    out: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Benchmark every size x channel of `profile` x padding mode; print aligned tables and return one dict per
    row.

    Times are medians of `repeats` calls after one warm-up. Every mode and its bare FFT pair are timed in
    turn within each round, and ratios (to the bare pair, and the speed-up over "2x") are medians of the
    per-round ratios, so load from other processes that comes and goes cancels out. The reference pads
    `reference_factor` x (>= 4) in float64. Rows also carry the error ratio over "2x" (error / error_2x)
    when "2x" is among the modes.
    """
    if reference_factor < 4:
        raise ValueError(f"reference_factor must be >= 4 for a converged reference, got {reference_factor}")
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    device = torch.device(device)
    timed = _timer(device)
    rows: list[dict[str, Any]] = []
    for shape in sizes:
        field64, field32 = _slm_fields(shape, seed, device)
        bench = grid_profile(profile.require("slm", "optics", "laser"), (shape[0], shape[1]))
        for channel in bench.channels:
            colour, geometry = channel.name, bench.geometry(channel.name)
            wavelength_m = geometry.wavelength_m
            roi = centred_slices(geometry.shape, geometry.roi)
            reference = _propagator(f"{reference_factor}x", geometry)(field64)[..., roi[0], roi[1]].clone()
            props = {mode: _propagator(mode, geometry) for mode in modes}
            bare_inputs = {mode: torch.zeros(p.plan.padded_shape, dtype=torch.complex64, device=device)
                           for mode, p in props.items()}
            ky, kx = next(iter(props.values())).plan.spread_fraction
            out("")
            out(f"{shape[0]}x{shape[1]} {colour} ({wavelength_m * 1e9:g} nm): K/N rows {ky:.2f}, cols {kx:.2f}"
                f" (K under half the grid: {_under_half(ky, kx)})")
            for mode, p in props.items():
                out(f"  plan {mode!s:>5}: {p.plan.describe()}")
            for mode, p in props.items():
                p(field32)
                _fft_pair(bare_inputs[mode])
            times: dict[Padding, list[float]] = {mode: [] for mode in modes}
            bare: dict[Padding, list[float]] = {mode: [] for mode in modes}
            for _ in range(repeats):
                for mode, p in props.items():
                    bare[mode].append(timed(_fft_pair, bare_inputs[mode]))
                    times[mode].append(timed(p, field32))
            block: list[dict[str, Any]] = []
            for mode, p in props.items():
                block.append({
                    "size": f"{shape[0]}x{shape[1]}",
                    "colour": colour,
                    "wavelength_nm": round(wavelength_m * 1e9, 3),
                    "mode": str(mode),
                    "padded": f"{p.plan.padded_shape[0]}x{p.plan.padded_shape[1]}",
                    "k_over_n_rows": round(ky, 4),
                    "k_over_n_cols": round(kx, 4),
                    "time_ms": statistics.median(times[mode]) * 1e3,
                    "bare_fft_ms": statistics.median(bare[mode]) * 1e3,
                    "ratio_to_bare": _median_ratio(times[mode], bare[mode]),
                    "roi_rel_l2": _relative_l2(_on_roi(p, field32, roi), reference),
                    "plan": p.plan.describe(),
                    "speedup_vs_2x": _median_ratio(times["2x"], times[mode]) if "2x" in times else None,
                })
            base = next((r for r in block if r["mode"] == "2x"), None)
            for r in block:
                r["error_vs_2x"] = r["roi_rel_l2"] / base["roi_rel_l2"] if base and base["roi_rel_l2"] else None
            _print_table(block, out)
            auto = next((r for r in block if r["mode"] == "auto"), None)
            if auto and base:
                out(f"  auto vs 2x: {auto['speedup_vs_2x']:.2f}x faster, error ratio {auto['error_vs_2x']:.2f}")
            rows += block
            del props, bare_inputs, reference
    if rows:
        out("")
        out("Summary")
        _print_table(rows, out, with_case=True)
    return rows


def _slm_fields(shape: tuple[int, int], seed: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """What a phase SLM shows: unit amplitude, uniformly random phase (seeded), in complex128 and complex64."""
    generator = torch.Generator().manual_seed(seed)
    phase = (2.0 * torch.rand(tuple(shape), generator=generator, dtype=torch.float64) - 1.0) * math.pi
    field64 = torch.polar(torch.ones_like(phase), phase).to(device)
    return field64, field64.to(torch.complex64)


def _propagator(mode: Padding, geometry: Geometry) -> Propagator:
    """SLM -> target at `geometry` (without its iris) padded as `mode` says; ROI_MODE: "auto" computing the ROI."""
    window = None
    if mode == ROI_MODE:
        rows, cols = centred_slices(geometry.shape, geometry.roi)
        mode, window = "auto", (rows.start, geometry.roi[0], cols.start, geometry.roi[1])
    return Propagator(geometry.shape, geometry.distance_m, geometry.wavelength_m, geometry.pitch_m, padding=mode,
                      window=window)


def _on_roi(propagator: Propagator, field: torch.Tensor, roi: tuple[slice, slice]) -> torch.Tensor:
    """The propagated field on the ROI: a windowed propagator computes nothing else."""
    result = propagator(field)
    return result if propagator.plan.window is not None else result[..., roi[0], roi[1]]


def _median_ratio(numerators: list[float], denominators: list[float]) -> float:
    """Median over rounds of a / b: each pair was timed back to back, so load that drifts cancels out."""
    return statistics.median(a / b for a, b in zip(numerators, denominators))


def _under_half(ky: float, kx: float) -> str:
    axes = [name for name, k in (("rows", ky), ("cols", kx)) if k < 0.5]
    return " and ".join(axes) if axes else "neither axis"


def _print_table(rows: list[dict[str, Any]], out: Callable[[str], None], with_case: bool = False) -> None:
    """Aligned columns: one line per row."""
    def fmt(value: Any, spec: str) -> str:
        return "-" if value is None else format(value, spec)

    header = (["size", "colour"] if with_case else []) + [
        "mode", "padded", "K/N rows", "K/N cols", "ms", "bare FFT ms", "/bare", "ROI rel L2", "2x/this", "err/2x"]
    lines = [header]
    for r in rows:
        lines.append(([r["size"], r["colour"]] if with_case else []) + [
            r["mode"], r["padded"], fmt(r["k_over_n_rows"], ".2f"), fmt(r["k_over_n_cols"], ".2f"),
            fmt(r["time_ms"], ".4g"), fmt(r["bare_fft_ms"], ".4g"), fmt(r["ratio_to_bare"], ".2f"),
            fmt(r["roi_rel_l2"], ".2e"), fmt(r["speedup_vs_2x"], ".2f"), fmt(r["error_vs_2x"], ".2f")])
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    for line in lines:
        out("  " + "  ".join(cell.rjust(width) for cell, width in zip(line, widths)))


def bench_planes(profile: Profile, count: int) -> list[float]:
    """`count` distances (m) evenly over the profile's depth range (its target plane +-5 % without one)."""
    optics = profile.section("optics")
    near, far = optics.depth_range_m or (0.95 * optics.distance_m, 1.05 * optics.distance_m)
    if count == 1:
        return [0.5 * (near + far)]
    return [near + (far - near) * k / (count - 1) for k in range(count)]


def run_multiplane_bench(
    profile: Profile,
    sizes: Sequence[tuple[int, int]] = PAPER_SIZES[:1],
    *,
    planes: int = 8,
    repeats: int = 5,
    seed: int = 0,
    device: str | torch.device = "cpu",
    out: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Per size and colour: one complex64 field to `planes` planes over the depth range, by one
    `MultiPlanePropagator` and by as many independent `Propagator`s (each padded for its own distance), timed in
    turn in each of `repeats` rounds after a warm-up; the ratio is the median of the per-round ratios. Errors, the
    largest over planes of the relative L2 on the ROI: the multi-plane result against itself in float64 (the shared
    grid: precision alone) and against a float64 `Propagator` per plane on its own grid, and the independent
    propagations against the latter."""
    if planes < 1 or repeats < 1:
        raise ValueError(f"planes and repeats must be >= 1, got {planes} and {repeats}")
    device = torch.device(device)
    timed = _timer(device)
    rows: list[dict[str, Any]] = []
    for shape in sizes:
        field64, field32 = _slm_fields(shape, seed, device)
        bench = grid_profile(profile.require("slm", "optics", "laser"), (shape[0], shape[1]))
        distances = bench_planes(bench, planes)
        for channel in bench.channels:
            geometry = bench.geometry(channel.name)
            roi = centred_slices(geometry.shape, geometry.roi)
            single = [Propagator(geometry.shape, z, geometry.wavelength_m, geometry.pitch_m) for z in distances]
            many = MultiPlanePropagator(geometry.shape, distances, geometry.wavelength_m, geometry.pitch_m)


            errors_shared, errors_many, errors_single = [], [], []
            stack, each = many(field32), _each(single, field32)
            shared = many(field64)  # float64 on the planes' shared grid: the float32 error alone
            for k, p in enumerate(single):
                own = Propagator(geometry.shape, p.plan.distance_m, geometry.wavelength_m, geometry.pitch_m)
                expected = own(field64)[..., roi[0], roi[1]]  # float64 on the plane's own grid
                errors_shared.append(_relative_l2(stack[k][..., roi[0], roi[1]], shared[k][..., roi[0], roi[1]]))
                errors_many.append(_relative_l2(stack[k][..., roi[0], roi[1]], expected))
                errors_single.append(_relative_l2(each[k][..., roi[0], roi[1]], expected))
            del stack, each, shared
            times_many, times_single = [], []
            for _ in range(repeats):
                times_single.append(timed(_each, single, field32))
                times_many.append(timed(many, field32))
            row = {
                "size": f"{shape[0]}x{shape[1]}",
                "colour": channel.name,
                "planes": planes,
                "distances_mm": f"{distances[0] * 1e3:g}..{distances[-1] * 1e3:g}",
                "padded": f"{many.plan.padded_shape[0]}x{many.plan.padded_shape[1]}",
                "multiplane_ms": statistics.median(times_many) * 1e3,
                "independent_ms": statistics.median(times_single) * 1e3,
                "ratio": _median_ratio(times_many, times_single),
                "multiplane_rel_l2_shared_grid": max(errors_shared),
                "multiplane_rel_l2": max(errors_many),
                "independent_rel_l2": max(errors_single),
            }
            rows.append(row)
            del single, many
    out("")
    out(f"One field to {planes} planes: one multi-plane propagation (1 forward FFT + {planes} inverse) against "
        f"{planes} independent propagations. Errors, largest ROI rel L2 over the planes, against float64: on the "
        "planes' shared grid (the farthest plane's) and on each plane's own grid")
    header = ["size", "colour", "planes mm", "padded", "multi ms", "independent ms", "multi/indep",
              "multi vs f64 shared", "multi vs f64 own", "indep vs f64 own"]
    lines = [header] + [[r["size"], r["colour"], r["distances_mm"], r["padded"], f"{r['multiplane_ms']:.4g}",
                         f"{r['independent_ms']:.4g}", f"{r['ratio']:.2f}", f"{r['multiplane_rel_l2_shared_grid']:.2e}",
                         f"{r['multiplane_rel_l2']:.2e}", f"{r['independent_rel_l2']:.2e}"] for r in rows]
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    for line in lines:
        out("  " + "  ".join(cell.rjust(width) for cell, width in zip(line, widths)))
    return rows


def _each(propagators: Sequence[Propagator], field: torch.Tensor) -> list[torch.Tensor]:
    """`field` propagated by each of `propagators` on its own."""
    return [p(field) for p in propagators]
