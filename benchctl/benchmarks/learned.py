"""`benchctl bench learned`: the learned methods side by side: parameters, inference time, training memory, quality.

Per method, in one run, on one grid (the profile's, or --size with pitch and distance kept and the ROI scaled,
as for training):
- trainable parameters;
- inference seconds per frame: the full network (generator, full-definition propagation, encoder) on one
  colour's target, median of `repeats` runs after one warm-up, under inference mode; on CUDA the device is
  synchronised around every timed run;
- peak memory of one training step (forward, propagation to the target plane, ROI loss, backward, Adam step,
  batch 1), each model in its own fresh subprocess. CPU: the process's peak resident set (VmHWM) during the
  step minus its resident set just before it (after imports, model, propagation kernels and input were set
  up; the peak is reset there through /proc/self/clear_refs). Not `getrusage`: in a freshly exec'd child
  Linux reports the parent's peak as ru_maxrss. CUDA: torch.cuda.max_memory_allocated during the step minus
  the memory allocated before it;
- PSNR / SSIM (amplitude, mean over colours and targets, displayed 8-bit phase, as `benchctl generate`
  scores) where a trained checkpoint that fits the grid is given or shipped;
- ratios against the family's baseline network (holonet, ccnn), measured in the same run:
  speed-up = baseline seconds / seconds, memory reduction = 1 - peak / baseline peak.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import torch

from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.geometry import grid_profile
from benchctl.calibration.setups import optical_setup
from benchctl.cgh import OpticalSetup
from benchctl.cgh.learned import LEARNED_METHODS, build_model, count_parameters, model_info
from benchctl.cgh.learned.models import VARIANTS
from benchctl.errors import BadValueError, BenchctlError
from benchctl.files import ensure_dir, write_csv
from benchctl.holograms.checkpoints import find_checkpoint, read_checkpoint
from benchctl.holograms.scene import compute_scene, resolve_method, usable_methods
from benchctl.optics.geometry import Geometry
from benchctl.profiles import Profile
from benchctl.targets import load_target, prepare_target, target_plane
from benchctl.training.training import ReconstructionLoss, peak_normalised, training_step

DEFAULT_TARGETS = ("chart:siemens", "chart:bars", "chart:text")
BASELINES = {"holonet": "holonet", "ccnn": "ccnn"}
"""The baseline network of each family, against which ratios are given."""


def _device() -> torch.device:
    return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def inference_seconds(model: torch.nn.Module, amplitude: torch.Tensor, repeats: int) -> float:
    """Median seconds of one forward pass (after a warm-up), synchronised on CUDA."""
    model.eval()
    device = amplitude.device
    times = []
    with torch.inference_mode():
        model(amplitude)
        _sync(device)
        for _ in range(repeats):
            start = time.perf_counter()
            model(amplitude)
            _sync(device)
            times.append(time.perf_counter() - start)
    return statistics.median(times)


_PEAK_NEEDS = "peak resident memory needs Linux's /proc/self/status and /proc/self/clear_refs"


def _proc_status() -> dict[str, int]:
    """VmRSS and VmHWM of this process in bytes (Linux); a BenchctlError where /proc does not give them."""
    try:
        lines = Path("/proc/self/status").read_text().splitlines()
    except OSError:
        lines = []
    values = {}
    for line in lines:
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = int(rest.split()[0]) * 1024
    if len(values) != 2:
        raise BenchctlError(_PEAK_NEEDS)
    return values


def _reset_peak() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def training_step_memory(method: str, geometry: dict[str, Any], device: str,
                         memory_cap: int | None = None) -> dict[str, Any]:
    """In this process: set up `method` for `geometry`, run one training step, return its peak memory.

    Meant to run in a fresh subprocess (see `measure_training_step`), one per model. `memory_cap` (bytes) caps the
    address space once the set-up is done, so libraries that load lazily while it runs are not refused.
    """
    dev = torch.device(device)
    setup = OpticalSetup.of(Geometry.from_dict(geometry))
    torch.manual_seed(0)
    model = build_model(method, setup).to(dev)
    optimiser = torch.optim.Adam(model.parameters(), lr=5e-4)
    amplitude = torch.zeros(1, 1, *setup.shape, device=dev)
    rows, cols = setup.roi_slices
    amplitude[..., rows, cols] = torch.rand(setup.roi, device=dev)  # content does not change memory
    amplitude = peak_normalised(amplitude)
    for propagator in (setup.slm_propagator(), setup.target_propagator()):
        propagator.kernel(torch.complex64, dev)
    loss_fn = ReconstructionLoss().to(dev)
    if memory_cap:
        _limit_memory(memory_cap)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
        before = torch.cuda.memory_allocated(dev)
        torch.cuda.reset_peak_memory_stats(dev)
        start, start_cpu = time.perf_counter(), time.process_time()
        try:
            training_step(model, optimiser, setup, amplitude, loss_fn)
        except torch.cuda.OutOfMemoryError:
            return {"out_of_memory": True, "total_bytes": torch.cuda.get_device_properties(dev).total_memory}
        torch.cuda.synchronize(dev)
        seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - start_cpu
        peak = torch.cuda.max_memory_allocated(dev) - before
        extra = {"reserved_bytes": torch.cuda.max_memory_reserved(dev),
                 "allocated_total_bytes": torch.cuda.max_memory_allocated(dev),
                 "total_bytes": torch.cuda.get_device_properties(dev).total_memory}
        how = "torch.cuda.max_memory_allocated during the step minus memory allocated before it"
    else:
        if not _reset_peak():
            raise BenchctlError(_PEAK_NEEDS)
        before = _proc_status()["VmRSS"]
        start, start_cpu = time.perf_counter(), time.process_time()
        training_step(model, optimiser, setup, amplitude, loss_fn)
        seconds, cpu_seconds = time.perf_counter() - start, time.process_time() - start_cpu
        peak = _proc_status()["VmHWM"] - before
        extra = {}
        how = "peak resident set (VmHWM, reset before the step) minus resident set before the step"
    return {"peak_bytes": int(peak), "baseline_bytes": int(before), "step_seconds": seconds,
            "step_cpu_seconds": cpu_seconds, "measure": how} | extra


OUT_OF_MEMORY = "out of memory"


def measure_training_step(method: str, setup: OpticalSetup, device: torch.device,
                          memory_cap: int | None = None, env: dict[str, str] | None = None) -> dict[str, Any]:
    """`training_step_memory` for `method` in a fresh Python subprocess; its JSON result.

    `memory_cap` (bytes) limits the subprocess's address space (CPU; the kernel's out-of-memory killer is told to
    pick it first): a step that would need more gives {"out_of_memory": True} instead of a traceback or a machine
    that swaps or kills its neighbours."""
    request = json.dumps({"method": method, "geometry": setup.geometry.to_dict(), "device": str(device),
                          "memory_cap": memory_cap})
    proc = subprocess.run([sys.executable, "-m", "benchctl.benchmarks.learned", request], capture_output=True,
                          text=True, env=env or os.environ.copy(), check=False)
    if memory_cap and proc.returncode in (-9, 137):  # killed by the kernel's out-of-memory killer
        return {"out_of_memory": True, "cap_bytes": memory_cap}
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise BenchctlError(f"training-step subprocess for {method} failed (exit {proc.returncode}): "
                            + " | ".join(tail))
    return json.loads(proc.stdout.strip().splitlines()[-1]) | ({"cap_bytes": memory_cap} if memory_cap else {})


PAPER_MEMORY_MIB: dict[str, dict[str, float | None]] = {
    "holonet": {"1088x1920": 9355, "2176x3840": None},
    "holonet-dcm2": {"1088x1920": 5647, "2176x3840": 14455},
    "holonet-dcm4": {"1088x1920": 3337, "2176x3840": 7299},
    "holonet-pyramid": {"1088x1920": 5351, "2176x3840": 12083},
    "ccnn": {"2176x3840": 5957, "4352x7680": 19573},
    "ccnn-dcm4": {"2176x3840": 5265, "4352x7680": 17041},
}
"""The paper's training memory (MiB, RTX 3090 with 24 GB; None: out of memory) per network and grid (Tables 1
and 2); the paper trains CCNN only at 4K and 8K and HoloNet's family at 1080p and 4K."""
MEMORY_TABLE_METHODS = tuple(PAPER_MEMORY_MIB)
MEMORY_TABLE_GRIDS = ((1088, 1920), (2176, 3840), (4352, 7680))


def run_memory_table(profile: Profile, *, grids: Sequence[tuple[int, int]] = MEMORY_TABLE_GRIDS,
                     methods: Sequence[str] = MEMORY_TABLE_METHODS, memory_cap_gib: float = 20.0,
                     out_dir: Path | None = None, out: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """One training step per method and grid (the paper's geometry: pitch and distance kept, ROI scaled), each in
    a fresh subprocess whose address space is capped at `memory_cap_gib`: the peak memory and the time of the
    step, or "out of memory above the cap"; a method out of memory on a grid is not tried on larger ones."""
    unknown = [m for m in methods if m not in LEARNED_METHODS]
    if unknown:
        raise BadValueError(f"unknown learned method(s) {', '.join(unknown)}; known: {', '.join(LEARNED_METHODS)}")
    if not 1 <= memory_cap_gib <= 4096:
        raise BadValueError(f"--memory-cap must lie between 1 and 4096 GiB, got {memory_cap_gib:g}")
    cap = int(memory_cap_gib * 2**30)
    device = _device()
    out(f"one training step (batch 1, forward, propagation, ROI loss, backward, Adam) per method and grid, on "
        f"{device} ({torch.get_num_threads()} threads), each in a fresh subprocess with its address space capped "
        f"at {memory_cap_gib:g} GiB")
    rows = []
    for method in methods:
        too_big = None
        for grid in sorted(grids, key=lambda g: g[0] * g[1]):
            label = f"{grid[0]}x{grid[1]}"
            row: dict[str, Any] = {"method": method, "grid": label, "device": str(device),
                                   "cap_gib": memory_cap_gib,
                                   "paper_mib": PAPER_MEMORY_MIB.get(method, {}).get(label, "")}
            if too_big is not None:
                row |= {"result": f"{OUT_OF_MEMORY} (at {too_big} already)"}
            else:
                bench = grid_profile(profile.require("slm", "optics", "laser"), grid)
                setup = optical_setup(bench, bench.channels[0].name)
                measured = measure_training_step(method, setup, device, cap)
                if measured.get("out_of_memory"):
                    too_big = label
                    row |= {"result": f"{OUT_OF_MEMORY} above {memory_cap_gib:g} GiB"}
                else:
                    row |= {"result": "ok", "peak_mib": round(measured["peak_bytes"] / 2**20),
                            "step_seconds": round(measured["step_seconds"], 2),
                            "step_cpu_seconds": round(measured["step_cpu_seconds"], 2),
                            "before_mib": round(measured["baseline_bytes"] / 2**20)}
            rows.append(row)
            out(f"  {method:<16} {label:>10}: " + (f"{row['peak_mib']:>7,} MiB, {row['step_seconds']:.1f} s "
                                                   f"({row['step_cpu_seconds']:.1f} CPU-s)"
                                                   if row["result"] == "ok" else row["result"]))
    if out_dir is not None:
        out(f"wrote {write_csv(ensure_dir(Path(out_dir)) / 'learned_memory.csv', rows)}")
    return rows


def _checkpoints(paths: Sequence[Path], methods: list[str], bench: Profile) -> dict[str, Path]:
    """Method -> checkpoint: the given files (each names its method), else shipped ones that fit the grid."""
    chosen: dict[str, Path] = {}
    for path in paths:
        method = read_checkpoint(path).method
        if method not in methods:
            raise BadValueError(f"--checkpoint {path} holds {method}, which is not among --methods")
        resolve_method(method, bench, path)  # refused here, naming the differences, unless it fits the grid
        chosen[method] = Path(path)
    usable = usable_methods(bench)
    for method in methods:
        if method in usable and method not in chosen:
            found = find_checkpoint(method, bench)
            assert found is not None
            chosen[method] = found
    return chosen


def _scores(bench: Profile, method: str, checkpoint: Path, targets: Sequence[str]) -> dict[str, float]:
    grid, roi = bench.section("slm").shape, bench.section("optics").roi
    psnrs, ssims = [], []
    for target in targets:
        scene = compute_scene(prepare_target(load_target(target, size=roi), grid, roi), Calibrated(bench), method,
                              checkpoint=checkpoint)
        for colour in scene.colours:
            if not colour.skipped:
                psnrs.append(colour.scores["psnr_amplitude_db"])
                ssims.append(colour.scores["ssim_amplitude"])
    return {"psnr_amplitude_db": statistics.mean(psnrs), "ssim_amplitude": statistics.mean(ssims)}


def run_learned_bench(
    profile: Profile,
    *,
    size: tuple[int, int] | None = None,
    methods: Sequence[str] | None = None,
    checkpoints: Sequence[Path] = (),
    repeats: int = 3,
    targets: Sequence[str] = DEFAULT_TARGETS,
    training_memory: bool = True,
    out_dir: Path | None = None,
    out: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Measure each learned method side by side (see the module doc); print a table, write learned.csv."""
    bench = grid_profile(profile, size) if size else profile.require("slm", "optics", "laser")
    names = list(methods or LEARNED_METHODS)
    for name in names:
        if name not in LEARNED_METHODS:
            raise BadValueError(f"unknown learned method {name!r}; known: {', '.join(LEARNED_METHODS)}")
    baselines = [BASELINES[VARIANTS[n].family] for n in names if BASELINES[VARIANTS[n].family] not in names]
    if baselines:
        out(f"adding the baseline network(s) {', '.join(dict.fromkeys(baselines))} for the ratios")
        names = list(dict.fromkeys(baselines)) + names
    names = sorted(dict.fromkeys(names), key=LEARNED_METHODS.index)
    chosen = _checkpoints(checkpoints, names, bench)
    device = _device()
    channel = bench.channels[0]
    setup = optical_setup(bench, channel.name)
    grid, roi = setup.shape, setup.roi
    plane = prepare_target(load_target(DEFAULT_TARGETS[0], size=roi), grid, roi)[target_plane(channel)]
    amplitude = (plane / plane.max())[None, None].to(device)
    out(f"grid {grid[0]}x{grid[1]}, ROI {roi[0]}x{roi[1]}, {channel.name} {channel.wavelength_nm:g} nm, pitch "
        f"{bench.section('slm').pitch_um:g} um, distance {bench.section('optics').distance_mm:g} mm, on {device}"
        f" ({torch.get_num_threads()} threads); inference: median of {repeats} after a warm-up")
    rows = []
    for name in names:
        torch.manual_seed(0)
        path = chosen.get(name)
        model = (read_checkpoint(path).model(channel.name, device) if path is not None
                 else build_model(name, setup).to(device))
        row: dict[str, Any] = {"method": name, "family": VARIANTS[name].family, "tier": model_info(name, grid)["tier"],
                               "grid": f"{grid[0]}x{grid[1]}", "device": str(device),
                               "parameters": count_parameters(model),
                               "inference_seconds": inference_seconds(model, amplitude, repeats)}
        del model
        if training_memory:
            memory = measure_training_step(name, setup, device)
            row |= {"train_step_peak_mib": memory["peak_bytes"] / 2**20, "train_step_seconds": memory["step_seconds"],
                    "memory_measure": memory["measure"]}
        if path is not None:
            row |= _scores(bench, name, path, targets) | {"checkpoint": str(path)}
        rows.append(row)
        out(f"  measured {name}")
    _add_ratios(rows)
    for line in format_table(rows):
        out(line)
    if training_memory and rows:
        out(f"training memory: {rows[0]['memory_measure']}, one fresh subprocess per model")
    if out_dir is not None:
        out(f"wrote {write_csv(ensure_dir(Path(out_dir)) / 'learned.csv', rows)}")
    return rows


def with_baselines(rows: list[dict[str, Any]]) -> Iterator[tuple[dict[str, Any], dict[str, Any]]]:
    """Each row (a dict with "method" and "family") with its family's baseline row, the baseline's name recorded in
    the row as "baseline"; rows whose baseline was not measured are left out."""
    by_name = {r["method"]: r for r in rows}
    for row in rows:
        base = by_name.get(BASELINES[row["family"]])
        if base is not None:
            row["baseline"] = base["method"]
            yield row, base


def _add_ratios(rows: list[dict[str, Any]]) -> None:
    for row, base in with_baselines(rows):
        row["parameters_ratio"] = row["parameters"] / base["parameters"]
        row["speedup"] = base["inference_seconds"] / row["inference_seconds"]
        if "train_step_peak_mib" in row and base.get("train_step_peak_mib"):
            row["memory_reduction_pct"] = 100.0 * (1.0 - row["train_step_peak_mib"] / base["train_step_peak_mib"])


def format_table(rows: Sequence[dict[str, Any]]) -> list[str]:
    """The printed table: one line per method, ratios against the family's baseline."""
    def num(row: dict[str, Any], key: str, fmt: str) -> str:
        return format(row[key], fmt) if key in row else "-"

    header = (f"{'method':<16} {'params':>10} {'x params':>8} {'s/frame':>9} {'speed-up':>8} {'train MiB':>10} "
              f"{'mem -%':>7} {'PSNR amp':>9} {'SSIM amp':>9}")
    lines = [header]
    for r in rows:
        lines.append(f"{r['method']:<16} {r['parameters']:>10,} {num(r, 'parameters_ratio', '.2f'):>8} "
                     f"{r['inference_seconds']:>9.4f} {num(r, 'speedup', '.2f'):>8} "
                     f"{num(r, 'train_step_peak_mib', '.0f'):>10} {num(r, 'memory_reduction_pct', '.1f'):>7} "
                     f"{num(r, 'psnr_amplitude_db', '.2f'):>9} {num(r, 'ssim_amplitude', '.3f'):>9}")
    return lines


def _limit_memory(cap: int) -> None:
    """Cap this process's address space at `cap` bytes and make it the out-of-memory killer's first choice."""
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    try:
        Path("/proc/self/oom_score_adj").write_text("1000")
    except OSError:
        pass


# how torch's CPU allocators and oneDNN (which cannot map its workspace) word a refused allocation
_ALLOCATION_FAILED = ("memory", "allocate", "could not create a primitive")


def _child(argv: Sequence[str]) -> int:
    request = json.loads(argv[0])
    try:
        result = training_step_memory(request["method"], request["geometry"], request["device"],
                                      request.get("memory_cap"))
    except MemoryError:
        result = {"out_of_memory": True}
    except RuntimeError as exc:
        if not any(words in str(exc).lower() for words in _ALLOCATION_FAILED):
            raise
        result = {"out_of_memory": True, "detail": str(exc).splitlines()[0]}
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(_child(sys.argv[1:]))
