"""`benchctl bench reproduce`: the quality side of the DCM paper (its Tables 1, 2 and 4), each network trained
until its curve has flattened, with several seeds, on a bench scaled to a CPU-trainable grid.

A run is a folder: `plan.json` lists its jobs (one method, seed and bench variant each: the Fresnel-scaled
bench with its iris, or without it for the low-definition ablation's physical test), each job trains in its
own subprocess with its own torch threads (`reproduce_job.py`: stopping rule, exact resume), `--jobs` of them
at a time, and the report (`reproduce_report.py`) is built from the finished jobs. Interrupted at any point,
`--resume DIR` continues: a finished job is never retrained, an interrupted one continues from its last
saved state. Then the training-step memory of each method (a fresh subprocess each, as `bench learned`
measures it) and DPAC on the same photographs, the classical reference.

The recipe is the paper's where the paper gives one: Adam (0.9, 0.999) at lr 5e-4 ("for our method, we set the
learning rate to 5e-4"; its public code's default is 1e-3, at which the pyramid's stacked LFMNs clamp their
whole output at +-pi and stop learning), batch 1, random flips. The loss is MSE on the ROI after the
least-squares scale (the paper adds a VGG19 perceptual term at 1080p; no weights are downloaded here).
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from benchctl.benchmarks.learned import measure_training_step
from benchctl.benchmarks.reproduce_job import (DEFAULT_HELD_OUT, JOB_DEVICE_ENV, bench_for, job_dir, read_done,
                                               read_plan)
from benchctl.benchmarks.reproduce_report import write_report
from benchctl.benchmarks.reproduce_slurm import check_partition, collect
from benchctl.calibration.setups import optical_setup
from benchctl.cgh.learned import LEARNED_METHODS
from benchctl.errors import BadValueError, BenchctlError
from benchctl.files import ensure_dir, write_json
from benchctl.memory import size_text
from benchctl.profiles import Profile
from benchctl.training.data import image_sources
from benchctl.training.device import VISIBLE_ENV, gpu_slots, resolve_device
from benchctl.training.schedule import Schedule

DEFAULT_METHODS = ("holonet", "holonet-dcm2", "holonet-dcm4", "holonet-pyramid", "holonet-ps2", "holonet-ps4",
                   "holonet-lowdef2", "holonet-dcm2-nolfm", "holonet-dcm2-noeccm", "holonet-dcm2-nogrn", "ccnn",
                   "ccnn-dcm4")
SEEDED = ("holonet", "holonet-dcm2", "holonet-dcm4", "holonet-pyramid", "ccnn", "ccnn-dcm4")
"""Methods trained with every seed; the ablations take the first seed only unless --ablation-seeds says more."""
NO_IRIS = ("holonet-dcm2", "holonet-lowdef2")
"""Trained once more without the bench's iris (the paper's code filters nothing at 1088 rows): the
low-definition ablation's physical explanation is tested by lowdef2 against dcm2 on that bench."""
DEFAULT_SIZE = (136, 240)
DEFAULT_DATA = "procedural:32+photos:train"
DEFAULT_SEEDS = (42, 43, 44)
PAPER_LR = 5e-4
MAX_SIZE_PIXELS = 1024 * 1024  # a CPU-trainable grid: larger ones take days per method here
POLL_S = 2.0
GPU_MEMORY_USE = 0.9  # of a GPU's memory its jobs may plan on: the CUDA context and the allocator's cache take some


def job_name(method: str, seed: int, iris: bool) -> str:
    return f"{method}{'' if iris else '@no-iris'}-s{seed}"


def plan_jobs(methods: Sequence[str], seeds: Sequence[int], ablation_seeds: Sequence[int],
              iris_test: bool) -> list[dict[str, Any]]:
    """The jobs in the order they run: every method's first seed (slowest first), the no-iris variants, then
    the further seeds, so an interrupted run already has one full table."""
    rounds: list[list[dict[str, Any]]] = []
    for method in methods:
        for k, seed in enumerate(seeds if method in SEEDED else ablation_seeds):
            while len(rounds) <= k:
                rounds.append([])
            rounds[k].append({"name": job_name(method, seed, True), "method": method, "seed": seed, "iris": True})
    if iris_test and all(m in methods for m in NO_IRIS):
        rounds.insert(1, [{"name": job_name(m, seeds[0], False), "method": m, "seed": seeds[0], "iris": False}
                          for m in NO_IRIS])
    return [job for jobs in rounds for job in jobs]


def _check(methods: Sequence[str], size: tuple[int, int], seeds: Sequence[int], lr: float, max_steps: int,
           min_steps: int, min_gain_db: float, threads: int, device: str, here: bool) -> None:
    unknown = [m for m in methods if m not in LEARNED_METHODS]
    if unknown:
        raise BadValueError(f"--methods: unknown learned method(s) {', '.join(unknown)}; known: "
                            f"{', '.join(LEARNED_METHODS)}")
    if not methods:
        raise BadValueError("--methods: give at least one learned method")
    # one line for a GPU that is not here; a SLURM plan's GPUs are on its nodes
    on_cpu = resolve_device(device).type == "cpu" if here else device == "cpu"
    if size[0] * size[1] > MAX_SIZE_PIXELS and on_cpu:
        raise BadValueError(f"--size {size[0]}x{size[1]}: at most {MAX_SIZE_PIXELS:,} pixels for a reproduction "
                            "run (each method trains for thousands of steps; 136x240 or 272x480 are CPU-trainable)")
    if not seeds:
        raise BadValueError("--seeds: give at least one seed")
    if not (0 < lr <= 0.1):  # also refuses NaN
        raise BadValueError(f"--lr must lie in (0, 0.1], got {lr:g}")
    if not 1 <= min_steps <= max_steps:
        raise BadValueError(f"--min-steps ({min_steps}) must lie between 1 and --max-steps ({max_steps})")
    if not 0 < min_gain_db < 100:
        raise BadValueError(f"--min-gain must lie in (0, 100) dB, got {min_gain_db:g}")
    if not 1 <= threads <= 256:
        raise BadValueError(f"--threads must lie between 1 and 256, got {threads}")


def new_plan(run_dir: Path, profile: Profile, *, size: tuple[int, int] = DEFAULT_SIZE,
             methods: Sequence[str] = DEFAULT_METHODS, seeds: Sequence[int] = DEFAULT_SEEDS,
             ablation_seeds: Sequence[int] | None = None, colour: str = "red", data: str = DEFAULT_DATA,
             lr: float = PAPER_LR, max_steps: int = 8192, min_steps: int = 1024, min_gain_db: float = 0.2,
             patience: int = 2,
             first_evaluation: int = 32, iris_test: bool = True, threads: int = 1, warmup: int = 0,
             decay: str = "none", held_out: str = DEFAULT_HELD_OUT, device: str = "cpu",
             slurm: dict[str, Any] | None = None, command: str | None = None) -> dict[str, Any]:
    """Write `run_dir/plan.json` for a new run (refusing a folder that holds one) and return the plan."""
    methods = list(dict.fromkeys(methods))
    _check(methods, size, seeds, lr, max_steps, min_steps, min_gain_db, threads, device, here=slurm is None)
    if slurm is not None:
        check_partition(slurm["partition"])  # one line for a missing SLURM or a wrong partition
    Schedule(lr, warmup, decay, max_steps)  # one line for a warm-up longer than the run or an unknown decay
    image_sources(held_out)  # one line for a held-out set that is not there
    run_dir = Path(run_dir)
    if (run_dir / "plan.json").exists():
        raise BenchctlError(f"{run_dir} already holds a reproduction run: continue it with --resume {run_dir}, or "
                            "give a new --out folder")
    if profile.path is None:
        raise BadValueError("bench reproduce needs a profile file (--profile)")
    profile.channel(colour)  # refuses an unknown colour, naming the channels
    if first_evaluation < 1 or first_evaluation & (first_evaluation - 1):
        raise BadValueError(f"--first-evaluation must be a power of two, got {first_evaluation}")
    if not 1 <= patience <= 8:
        raise BadValueError(f"--patience must lie between 1 and 8 doublings, got {patience}")
    plan = {"profile": str(Path(profile.path).resolve()), "size": list(size), "colour": colour, "data": data,
            "lr": lr, "max_steps": max_steps, "min_steps": min_steps, "min_gain_db": min_gain_db, "patience": patience,
            "first_evaluation": first_evaluation, "threads": threads, "seeds": list(seeds), "warmup": warmup,
            "decay": decay, "held_out": held_out, "device": device, "slurm": slurm,
            "jobs": plan_jobs(methods, seeds, list(ablation_seeds or seeds[:1]), iris_test), "command": command,
            "torch": torch.__version__}
    write_json(ensure_dir(run_dir) / "plan.json", plan)
    return plan


def job_env(plan: dict[str, Any], gpu: str | None) -> dict[str, str]:
    """The environment of one job's subprocess: its torch threads and, on a GPU, that GPU alone (cuda:0 inside)."""
    env = os.environ | {"OMP_NUM_THREADS": str(plan["threads"]), "MKL_NUM_THREADS": str(plan["threads"])}
    if gpu is not None:
        env |= {VISIBLE_ENV: gpu, JOB_DEVICE_ENV: "cuda:0"}
    return env


def run_jobs(run_dir: Path, jobs: int, out: Callable[[str], None] = print, *, jobs_per_gpu: int = 1) -> list[str]:
    """Train every unfinished job of the plan, `jobs` subprocesses at a time on CPU, `jobs_per_gpu` per GPU on
    GPUs (each pinned to its GPU); the names of jobs that failed."""
    plan = read_plan(run_dir)
    slots = gpu_slots(plan.get("device", "cpu"), jobs_per_gpu)
    free: list[str | None] = slots if slots != [None] else [None] * jobs
    pending = [j["name"] for j in plan["jobs"] if read_done(run_dir, j["name"]) is None]
    total = len(plan["jobs"])
    where = (f"{jobs_per_gpu} per GPU on GPU(s) {', '.join(sorted(set(map(str, slots))))}" if slots != [None]
             else f"{plan['threads']} torch thread(s) each")
    out(f"{total - len(pending)} of {total} jobs finished; training {len(pending)}, {len(free)} at a time, {where} "
        f"(logs in {Path(run_dir) / 'jobs'}/<job>/log.txt)")
    running: dict[str, tuple[subprocess.Popen[bytes], str | None]] = {}
    failed: list[str] = []
    started = time.perf_counter()
    try:
        while pending or running:
            while pending and free:
                name, gpu = pending.pop(0), free.pop(0)
                log = (ensure_dir(job_dir(run_dir, name)) / "log.txt").open("ab")
                running[name] = (subprocess.Popen(
                    [sys.executable, "-m", "benchctl.benchmarks.reproduce_job", str(run_dir), name],
                    stdout=log, stderr=subprocess.STDOUT, env=job_env(plan, gpu)), gpu)
                log.close()
                out(f"[{time.perf_counter() - started:7.0f} s] started {name}" + (f" on GPU {gpu}" if gpu else ""))
            time.sleep(POLL_S)
            for name, (proc, gpu) in list(running.items()):
                if proc.poll() is None:
                    continue
                del running[name]
                free.append(gpu)
                line = finished_line(run_dir, name, proc.returncode)
                out(f"[{time.perf_counter() - started:7.0f} s] {line}")
                if line.startswith("FAILED"):
                    failed.append(name)
    except BaseException:
        for proc, _ in running.values():
            proc.terminate()
        for proc, _ in running.values():
            proc.wait()
        out(f"stopped; {', '.join(running)} keep their last saved state: continue with "
            f"benchctl bench reproduce --resume {run_dir}")
        raise
    return failed


def finished_line(run_dir: Path, name: str, returncode: int | None) -> str:
    """What became of a job whose process ended: 'finished NAME: ...' or 'FAILED NAME (exit N): log tail'."""
    done = read_done(run_dir, name)
    if returncode != 0 or done is None:
        log = job_dir(run_dir, name) / "log.txt"
        tail = log.read_text(errors="replace").strip().splitlines()[-3:] if log.is_file() else ["no log"]
        return f"FAILED {name} (exit {returncode}): " + " | ".join(tail)
    last = done["curve"][-1] if done["curve"] else None
    clock = (f"{done['gpu_seconds'] / 60:.1f} GPU-min" if done.get("gpu_seconds")
             else f"{done['cpu_seconds'] / 60:.1f} CPU-min")
    return (f"finished {name}: {done['reason']} at step {done['steps']} ({clock})"
            + (f", held-out {last['psnr']:.2f} dB" if last else ""))


def measure_memory(run_dir: Path, out: Callable[[str], None] = print, *, jobs_per_gpu: int = 1) -> dict[str, float]:
    """Peak memory of one training step per method of the plan (MiB; a fresh subprocess each, on the plan's
    device, pinned to its first GPU), kept in memory.json so a resumed run measures only what is missing. On a
    GPU this is the pixel cap: a method whose step, `jobs_per_gpu` times over, does not fit is refused."""
    plan = read_plan(run_dir)
    path = Path(run_dir) / "memory.json"
    memory: dict[str, float] = json.loads(path.read_text()) if path.is_file() else {}
    gpu = gpu_slots(plan.get("device", "cpu"), 1)[0]
    for job in plan["jobs"]:
        if job["method"] in memory or not job["iris"]:
            continue
        bench = bench_for(plan, job)
        setup = optical_setup(bench, bench.channel(plan["colour"]).name)
        step = measure_training_step(job["method"], setup, torch.device("cuda:0" if gpu else "cpu"),
                                     env=job_env(plan, gpu))
        if step.get("out_of_memory"):
            raise BenchctlError(f"one training step of {job['method']} at {plan['size'][0]}x{plan['size'][1]} does "
                                f"not fit in GPU {gpu}'s memory: use a smaller --size or fewer --jobs-per-gpu")
        if gpu is not None and step["allocated_total_bytes"] * jobs_per_gpu > GPU_MEMORY_USE * step["total_bytes"]:
            raise BenchctlError(
                f"{job['method']} at {plan['size'][0]}x{plan['size'][1]} takes "
                f"{size_text(step['allocated_total_bytes'])} of GPU memory per job (one training step measured on "
                f"GPU {gpu}); {jobs_per_gpu} job(s) per GPU "
                f"need more than {GPU_MEMORY_USE:.0%} of its {size_text(step['total_bytes'])}: use fewer "
                "--jobs-per-gpu or a smaller --size")
        memory[job["method"]] = step["peak_bytes"] / 2**20
        out(f"training-step memory of {job['method']}: {memory[job['method']]:.0f} MiB")
        write_json(path, memory)
    return memory


def run_reproduction(run_dir: Path, *, jobs: int = 2, jobs_per_gpu: int = 1, memory: bool = True,
                     wait: bool = False, out: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Train what the plan in `run_dir` still needs (locally, or on SLURM where the plan says so: submitted or
    collected, and with `wait` until it is done), measure memory, write the report; its table rows."""
    plan = read_plan(run_dir)
    if plan.get("slurm"):
        unfinished = collect(run_dir, plan, out, wait=wait)
        rows = write_report(run_dir, out)
        if unfinished:
            out(f"{len(unfinished)} job(s) not finished on SLURM yet; the report covers the finished ones; collect "
                f"again with: benchctl bench reproduce --resume {run_dir}" + ("" if wait else " [--wait]"))
        return rows
    on_gpu = resolve_device(read_plan(run_dir).get("device", "cpu")).type == "cuda"
    if on_gpu:  # the GPU's pixel cap: measured before anything trains
        measure_memory(run_dir, out, jobs_per_gpu=jobs_per_gpu)
    failed = run_jobs(run_dir, jobs, out, jobs_per_gpu=jobs_per_gpu)
    if memory and not on_gpu:
        measure_memory(run_dir, out)
    rows = write_report(run_dir, out)
    if failed:
        raise BenchctlError(f"{len(failed)} job(s) failed ({', '.join(failed)}); their logs are in "
                            f"{Path(run_dir) / 'jobs'}; the report covers the finished ones")
    return rows


def reproduce_command(profile: str | None, out_dir: Path, *, size: tuple[int, int], methods: Sequence[str],
                      seeds: Sequence[int], ablation_seeds: Sequence[int] | None, colour: str, data: str, lr: float,
                      max_steps: int, min_steps: int, min_gain_db: float, patience: int, iris_test: bool,
                      jobs: int, threads: int, warmup: int = 0, decay: str = "none",
                      held_out: str = DEFAULT_HELD_OUT, device: str = "cpu", jobs_per_gpu: int = 1,
                      slurm: dict[str, Any] | None = None) -> str:
    """The `benchctl bench reproduce` command line that asks for exactly these settings."""
    words = ["benchctl", "bench", "reproduce", *(["--profile", profile] if profile else []),
             "--size", f"{size[0]}x{size[1]}", "--methods", ",".join(methods),
             "--seeds", ",".join(map(str, seeds))]
    words += ["--ablation-seeds", ",".join(map(str, ablation_seeds))] if ablation_seeds else []
    words += ["--colour", colour, "--data", data, "--lr", f"{lr:g}", "--max-steps", str(max_steps),
              "--min-steps", str(min_steps), "--min-gain", f"{min_gain_db:g}", "--patience", str(patience)]
    words += ["--warmup", str(warmup)] if warmup else []
    words += ["--decay", decay] if decay != "none" else []
    words += ["--held-out", held_out] if held_out != DEFAULT_HELD_OUT else []
    words += [] if iris_test else ["--no-iris-test"]
    words += ["--jobs", str(jobs), "--threads", str(threads)]
    words += ["--device", device] if device != "cpu" else []
    words += ["--jobs-per-gpu", str(jobs_per_gpu)] if jobs_per_gpu != 1 else []
    words += ["--slurm", slurm["partition"], "--slurm-time", str(slurm["time_min"])] if slurm else []
    return shlex.join(words + ["--out", str(out_dir)])
