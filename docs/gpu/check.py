"""The GPU check of issue 36, run by docs/gpu/check.sh on a machine with one CUDA GPU (see README.md here).

Four parts, each timed and logged, each writing one file under $OUT (at most 8 files come back from the device
machine, so run folders go to a scratch folder):
  1. `bench reproduce` on the GPU: one job per main method, STEPS steps at SIZE, two jobs per GPU
     -> reproduce.csv (per job: steps, GPU seconds, steps/s, last held-out PSNR, device) and the pool's output;
  2. steps per second of one training step per method at SIZE and the first grid of GRIDS, in this process
     (warm-up steps first, CUDA-synchronised) -> timing.csv;
  3. a 2-process `torchrun` of `benchctl train` (nccl first; where nccl refuses two processes on one GPU, gloo
     with both processes on cuda:0) -> torchrun.txt;
  4. peak CUDA memory of one training step per method and grid (a fresh subprocess each: max_memory_allocated
     and max_memory_reserved) next to the CPU peaks of docs/reproduction/learned_memory.csv -> memory.csv.

Settings (environment): GPU_CHECK_DEVICE (cuda; cpu for the dry run on a machine without a GPU), GPU_CHECK_STEPS
(256), GPU_CHECK_SIZE (136x240), GPU_CHECK_GRIDS (1088x1920,2176x3840), GPU_CHECK_SCRATCH (scratch folder).
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

from benchctl.benchmarks.learned import measure_training_step
from benchctl.calibration.geometry import grid_profile
from benchctl.calibration.setups import optical_setup
from benchctl.cgh.learned import build_model
from benchctl.profiles import load_profile
from benchctl.training.training import ReconstructionLoss, peak_normalised, training_step

METHODS = tuple(os.environ.get("GPU_CHECK_METHODS",
                               "holonet,holonet-dcm2,holonet-dcm4,holonet-pyramid,ccnn,ccnn-dcm4").split(","))
DEVICE = os.environ.get("GPU_CHECK_DEVICE", "cuda")
STEPS = int(os.environ.get("GPU_CHECK_STEPS", "256"))
SIZE = os.environ.get("GPU_CHECK_SIZE", "136x240")
GRIDS = [g for g in os.environ.get("GPU_CHECK_GRIDS", "1088x1920,2176x3840").split(",") if g]
OUT = Path(os.environ.get("OUT") or "gpu-out")
SCRATCH = Path(os.environ.get("GPU_CHECK_SCRATCH") or "/tmp/benchctl-gpu-check")
CPU_MEMORY = Path(__file__).resolve().parents[1] / "reproduction" / "learned_memory.csv"


def log(line: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {line}", flush=True)


def grid(text: str) -> tuple[int, int]:
    rows, cols = text.lower().split("x")
    return int(rows), int(cols)


def benchctl(*args: str, env: dict[str, str] | None = None, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """`python -m benchctl ARGS` from this source tree, its output logged."""
    proc = subprocess.run([sys.executable, "-m", "benchctl", *args], capture_output=True, text=True,
                          env=os.environ | (env or {}), timeout=timeout, check=False)
    for line in (proc.stdout + proc.stderr).strip().splitlines()[-40:]:
        log(f"  | {line}")
    return proc


def part_reproduce() -> None:
    run = SCRATCH / "reproduce"
    log(f"1. bench reproduce: {', '.join(METHODS)}, seed 42, {STEPS} steps at {SIZE} on {DEVICE}, 2 jobs per GPU")
    start = time.perf_counter()
    proc = benchctl("bench", "reproduce", "--profile", "simulated", "--size", SIZE, "--methods", ",".join(METHODS),
                    "--seeds", "42", "--no-iris-test", "--max-steps", str(STEPS), "--min-steps", str(STEPS),
                    "--warmup", str(min(16, STEPS // 4)), "--decay", "cosine", "--device", DEVICE,
                    "--jobs-per-gpu", "2", "--jobs", "2", "--out", str(run), timeout=600)
    log(f"   exit {proc.returncode} after {time.perf_counter() - start:.0f} s")
    rows = []
    for job in sorted((run / "jobs").glob("*/done.json")):
        done = json.loads(job.read_text())
        seconds = done.get("gpu_seconds") or done["wall_seconds"]
        rows.append({"job": done["name"], "device": done.get("device"), "reason": done["reason"],
                     "steps": done["steps"], "train_seconds": seconds, "steps_per_s": round(done["steps"] / seconds, 1),
                     "held_out_psnr_db": round(done["curve"][-1]["psnr"], 2), "cpu_seconds": done["cpu_seconds"]})
    write_csv("reproduce.csv", rows)
    (OUT / "reproduce.md").write_text((run / "reproduction.md").read_text() if (run / "reproduction.md").is_file()
                                      else "no report: see check.log\n")
    if proc.returncode != 0 or len(rows) != len(METHODS):
        raise SystemExit(f"bench reproduce on {DEVICE} failed: {len(rows)} of {len(METHODS)} jobs finished")


def part_timing() -> None:
    log(f"2. training steps per second on {DEVICE} (10 warm-up steps, then 30 timed, synchronised)")
    profile = load_profile("simulated")
    device = torch.device(DEVICE)
    rows = []
    for size in [SIZE, *GRIDS[:1]]:
        setup = optical_setup(grid_profile(profile, grid(size)), "red")
        for method in METHODS:
            torch.manual_seed(0)
            model = build_model(method, setup).to(device)
            optimiser = torch.optim.Adam(model.parameters(), lr=5e-4)
            amplitude = peak_normalised(torch.rand(1, 1, *setup.shape, device=device))
            loss = ReconstructionLoss().to(device)
            timed = 30 if device.type == "cuda" else 2
            for k in range(10 + timed if device.type == "cuda" else 1 + timed):
                if k == (10 if device.type == "cuda" else 1):
                    if device.type == "cuda":
                        torch.cuda.synchronize(device)
                    start = time.perf_counter()
                training_step(model, optimiser, setup, amplitude, loss)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            rate = timed / (time.perf_counter() - start)
            assert next(model.parameters()).device.type == device.type  # the model trained where it was asked to
            rows.append({"method": method, "grid": size, "device": str(device), "steps_per_s": round(rate, 2)})
            log(f"   {method:<16} {size:>10}: {rate:8.2f} steps/s")
            del model, optimiser
            if device.type == "cuda":
                torch.cuda.empty_cache()
    write_csv("timing.csv", rows)


def part_torchrun() -> None:
    log("3. torchrun, 2 processes, benchctl train --method holonet-dcm2 (4 steps) on one GPU")
    lines = []
    for backend in ("nccl", "gloo") if DEVICE == "cuda" else ("gloo",):
        out = SCRATCH / f"torchrun-{backend}"
        proc = subprocess.run(
            [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", "-m", "benchctl",
             "train", "--method", "holonet-dcm2", "--data", "procedural:8", "--profile", "simulated", "--size", SIZE,
             "--colours", "red", "--epochs", "1", "--max-steps", "4", "--val-fraction", "0.25", "--warmup", "2",
             "--device", DEVICE, "--out", str(out)],
            capture_output=True, text=True, env=os.environ | {"BENCHCTL_DDP_BACKEND": backend}, timeout=120,
            check=False)
        text = (proc.stdout + proc.stderr).strip().splitlines()
        meta = json.loads((out / "holonet-dcm2.json").read_text()) if (out / "holonet-dcm2.json").is_file() else {}
        training = meta.get("training", {})
        lines += [f"backend {backend}: exit {proc.returncode}; processes {training.get('processes')}, device "
                  f"{training.get('device')}, steps {training.get('steps')}", *(f"  | {t}" for t in text[-25:]), ""]
        log(lines[-len(text[-25:]) - 2])
        if proc.returncode == 0:
            lines.append(f"RESULT: 2-rank torchrun trained with backend {backend}")
            break
    else:
        lines.append("RESULT: 2-rank torchrun failed with every backend")
    (OUT / "torchrun.txt").write_text("\n".join(lines) + "\n")
    log(f"   {lines[-1]}")


def part_memory() -> None:
    log(f"4. peak memory of one training step per method at {', '.join(GRIDS)} on {DEVICE} (fresh subprocess each)")
    cpu = {(r["method"], r["grid"]): r for r in csv.DictReader(CPU_MEMORY.open())} if CPU_MEMORY.is_file() else {}
    profile = load_profile("simulated")
    rows = []
    for method in METHODS:
        for size in GRIDS:
            setup = optical_setup(grid_profile(profile, grid(size)), "red")
            start = time.perf_counter()
            step = measure_training_step(method, setup, torch.device(DEVICE))
            reference = cpu.get((method, size), {})
            row = {"method": method, "grid": size, "device": DEVICE,
                   "step_peak_mib": round(step["peak_bytes"] / 2**20) if "peak_bytes" in step else "",
                   "max_allocated_mib": round(step.get("allocated_total_bytes", 0) / 2**20) or "",
                   "max_reserved_mib": round(step.get("reserved_bytes", 0) / 2**20) or "",
                   "out_of_memory": bool(step.get("out_of_memory")),
                   "step_seconds": round(step.get("step_seconds", 0.0), 3),
                   "cpu_peak_mib": reference.get("peak_mib", ""), "cpu_result": reference.get("result", ""),
                   "paper_mib": reference.get("paper_mib", "")}
            rows.append(row)
            write_csv("memory.csv", rows)  # row by row: a run stopped at its time limit keeps what it measured
            log(f"   {method:<16} {size:>10}: step {row['step_peak_mib']} MiB, allocated {row['max_allocated_mib']} "
                f"MiB, reserved {row['max_reserved_mib']} MiB (CPU {row['cpu_peak_mib'] or row['cpu_result']}), "
                f"{time.perf_counter() - start:.0f} s")


def write_csv(name: str, rows: list[dict[str, object]]) -> None:
    if not rows:
        (OUT / name).write_text("")
        return
    with (OUT / name).open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    SCRATCH.mkdir(parents=True, exist_ok=True)
    device = torch.device(DEVICE)
    cuda = device.type == "cuda"
    info = {"torch": torch.__version__, "cuda": torch.version.cuda, "device": DEVICE,
            "gpu": torch.cuda.get_device_name(device) if cuda else None,
            "gpu_memory_bytes": torch.cuda.get_device_properties(device).total_memory if cuda else None,
            "python": sys.version.split()[0], "steps": STEPS, "size": SIZE, "grids": GRIDS}
    (OUT / "env.json").write_text(json.dumps(info, indent=2) + "\n")
    log(f"GPU check: {info}")
    failures = []
    for part in (part_reproduce, part_timing, part_torchrun, part_memory):
        start = time.perf_counter()
        try:
            part()
        except (Exception, SystemExit) as exc:  # the other parts still run; the exit status says it failed
            failures.append(f"{part.__name__}: {exc}")
            log(f"FAILED {part.__name__}: {exc!r}")
        log(f"   {part.__name__} took {time.perf_counter() - start:.0f} s")
    log("all parts passed" if not failures else f"{len(failures)} part(s) failed: {'; '.join(failures)}")
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
