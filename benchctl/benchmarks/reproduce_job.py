"""One training job of `benchctl bench reproduce`: one method, one seed, one bench variant, trained until its
validation score flattens, resumable exactly at any interruption.

A job trains with the `benchctl train` recipe (seeded image order and flips per step, Adam, MSE on the ROI
after the least-squares scale, batch 1) and is evaluated on a schedule of half-octave steps (32, 45, 64, 91,
128, ...): on validation images never trained on (procedural images from VALIDATION_FIRST on), which decide
when it stops, and on the held-out photographs, which the tables report. It stops once `patience`
power-of-two steps in a row (from `min_steps` on) each gained less than `min_gain_db` over their doubling of
steps (each side the mean of its two half-octave evaluations, to halve the noise of batch-1 training; more
than one in a row, so that one dip of a noisy curve does not end it), at the step cap, or when the network
stops learning or diverges (`health.TrainingHealth`); `done.json` says which.

Its state (weights, Adam's state, step, clocks and the curve) is written atomically at every evaluation and
every `SAVE_EVERY_S` seconds, and kept when the job ends (a later run with a higher cap can continue it); the
data order depends on the step alone, so a resumed job continues exactly.

    python -m benchctl.benchmarks.reproduce_job RUN_DIR JOB_NAME
"""

from __future__ import annotations

import io
import json
import math
import os
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import msgspec
import torch

from benchctl.benchmarks.learned import inference_seconds
from benchctl.benchmarks.speed_vs_error import resized_profile
from benchctl.calibration.setups import optical_setup
from benchctl.cgh.learned import build_model
from benchctl.devices.slm import slm_for
from benchctl.errors import BenchctlError
from benchctl.files import atomic_write_bytes, ensure_dir, write_json
from benchctl.optics import amplitude_scores, crop_roi, lsq_scale
from benchctl.profiles import Profile, load_profile
from benchctl.targets import prepare_target, target_plane
from benchctl.training.data import ImageSource, image_sources
from benchctl.training.device import StepClock, resolve_device
from benchctl.training.health import TrainingHealth
from benchctl.training.schedule import Schedule
from benchctl.training.training import (
    ReconstructionLoss,
    epoch_flips,
    epoch_order,
    load_targets,
    peak_normalised,
    training_step,
)

CPU = torch.device("cpu")
JOB_DEVICE_ENV = "BENCHCTL_JOB_DEVICE"  # the device a pool pinned this job to (cuda:0 of its CUDA_VISIBLE_DEVICES)
DEFAULT_HELD_OUT = "photos:eval"
VALIDATION_FIRST = 100_000  # procedural images from here on are nobody's training data (procedural:N starts at 0)
VALIDATION_COUNT = 8
SAVE_EVERY_S = 120.0


@dataclass
class Evaluation:
    """Scores at one step: validation (stopping rule) and held-out photographs (the tables), amplitude."""

    step: int
    cpu_seconds: float  # this job's CPU time in training steps so far (all threads; evaluation excluded)
    wall_seconds: float  # wall-clock time in training steps so far
    val_psnr: float
    psnr: float
    ssim: float
    gpu_seconds: float | None = None  # on a GPU: synchronised wall time in training steps (device.StepClock)


def schedule(first: int, last: int) -> list[int]:
    """Evaluation steps: half-octaves from `first` (round(first * 2^(k/2))) up to and including `last`."""
    steps: list[int] = []
    k = 0
    while (step := round(first * 2 ** (k / 2))) < last:
        steps.append(step)
        k += 1
    return steps + [last]


def doubling_gain(curve: Sequence[Evaluation]) -> float | None:
    """Validation dB gained over the last doubling of steps: mean of the last two half-octave evaluations minus
    the mean of the two an octave earlier; None before there are four."""
    if len(curve) < 4:
        return None
    return (curve[-1].val_psnr + curve[-2].val_psnr - curve[-3].val_psnr - curve[-4].val_psnr) / 2


def flat_doublings(curve: Sequence[Evaluation], min_steps: int, min_gain_db: float) -> int:
    """How many power-of-two evaluations in a row (from `min_steps` on, counted back from the newest) gained less than
    `min_gain_db` over their doubling of steps."""
    count = 0
    for i in range(len(curve) - 1, -1, -1):
        step = curve[i].step
        if step < min_steps:
            break
        if not math.log2(step).is_integer():
            continue
        gain = doubling_gain(curve[:i + 1])
        if gain is None or gain >= min_gain_db:
            break
        count += 1
    return count


def bench_for(plan: dict[str, Any], job: dict[str, Any]) -> Profile:
    """The Fresnel-scaled bench of the plan, without the iris for a job that asks so."""
    bench = resized_profile(load_profile(plan["profile"]), tuple(plan["size"]))
    if not job.get("iris", True):
        optics = msgspec.structs.replace(bench.section("optics"), iris_fraction=None)
        bench = msgspec.structs.replace(bench, optics=optics)
    return bench


class Scorer:
    """Amplitude PSNR / SSIM of a model's 8-bit displayed holograms over a set of images, as `benchctl
    generate` scores a hologram (through the SLM's lookup table, ROI, least-squares scale)."""

    def __init__(self, bench: Profile, colour: str, images: Sequence[ImageSource],
                 device: torch.device = CPU) -> None:
        channel = bench.channel(colour)
        self.name = channel.name
        self.device = device
        self.setup = optical_setup(bench, channel.name)
        self.slm = slm_for(bench)
        grid, roi = self.setup.shape, self.setup.roi
        plane = target_plane(channel)
        self.names = [image.name for image in images]
        planes = [prepare_target(image.load(roi), grid, roi)[plane] for image in images]
        self.inputs = [peak_normalised(p[None, None]).to(device) for p in planes]
        self.targets = [crop_roi(p, roi).to(device) for p in planes]

    def score_each(self, model: torch.nn.Module) -> list[dict[str, Any]]:
        """Per image: its name, amplitude PSNR (dB) and SSIM."""
        model.eval()
        scores = []
        with torch.no_grad():
            for name, amplitude, target in zip(self.names, self.inputs, self.targets):
                gray = self.slm.encode(model(amplitude)[0, 0].cpu(), self.name)
                phase = torch.from_numpy(self.slm.decode(gray, self.name)).to(self.device)
                recon = self.setup.reconstruct_roi(phase)
                each = amplitude_scores(recon * lsq_scale(recon, target), target)
                scores.append({"image": name, "psnr": each["psnr_amplitude_db"], "ssim": each["ssim_amplitude"]})
        return scores

    def score(self, model: torch.nn.Module) -> tuple[float, float]:
        """Mean amplitude PSNR (dB) and SSIM over the images."""
        each = self.score_each(model)
        return statistics.mean(e["psnr"] for e in each), statistics.mean(e["ssim"] for e in each)


def job_dir(run_dir: Path, name: str) -> Path:
    return Path(run_dir) / "jobs" / name


def read_plan(run_dir: Path) -> dict[str, Any]:
    """A run's plan.json; a folder without one, or a plan that is not JSON, is one line naming the file."""
    path = Path(run_dir) / "plan.json"
    if not path.is_file():
        raise BenchctlError(f"{run_dir}: not a reproduction run (no plan.json); start one with --out {run_dir}")
    try:
        plan = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BenchctlError(f"{path}: not a readable plan ({exc})") from None
    if not isinstance(plan, dict):
        raise BenchctlError(f"{path}: not a readable plan (a JSON object is expected)")
    return plan


def read_done(run_dir: Path, name: str) -> dict[str, Any] | None:
    """A finished job's record (reason, steps, clocks, curve, inference time), None while it is not finished."""
    path = job_dir(run_dir, name) / "done.json"
    return json.loads(path.read_text()) if path.is_file() else None


def read_progress(run_dir: Path, name: str) -> list[dict[str, Any]]:
    """The curve an unfinished job has recorded so far (empty before its first evaluation)."""
    path = job_dir(run_dir, name) / "curve.json"
    return json.loads(path.read_text()) if path.is_file() else []


def job_device(plan: dict[str, Any]) -> torch.device:
    """The device this job trains on: the one its pool pinned it to ($BENCHCTL_JOB_DEVICE, with the GPU chosen by
    CUDA_VISIBLE_DEVICES), else the plan's --device (under SLURM the scheduler sets CUDA_VISIBLE_DEVICES)."""
    return resolve_device(os.environ.get(JOB_DEVICE_ENV) or plan.get("device", "cpu"))


def run_job(run_dir: Path, name: str, out: Any = print) -> dict[str, Any]:
    """Train job `name` of the plan in `run_dir` to its end (resuming its saved state); its done record."""
    run_dir = Path(run_dir)
    plan = read_plan(run_dir)
    job = next(j for j in plan["jobs"] if j["name"] == name)
    folder = ensure_dir(job_dir(run_dir, name))
    torch.set_num_threads(int(plan["threads"]))
    device = job_device(plan)
    bench = bench_for(plan, job)
    colour = bench.channel(plan["colour"]).name
    setup = optical_setup(bench, colour)
    plane = target_plane(bench.channel(colour))
    train_images = load_targets(image_sources(plan["data"]), setup.shape, setup.roi)
    validation = Scorer(bench, colour, [ImageSource(f"procedural-{i}", index=i)
                                        for i in range(VALIDATION_FIRST, VALIDATION_FIRST + VALIDATION_COUNT)], device)
    held_out = Scorer(bench, colour, image_sources(plan.get("held_out", DEFAULT_HELD_OUT)), device)
    torch.manual_seed(job["seed"])
    model = build_model(job["method"], setup).to(device)
    optimiser = torch.optim.Adam(model.parameters(), lr=plan["lr"], betas=(0.9, 0.999))
    schedule_ = Schedule(plan["lr"], plan.get("warmup", 0), plan.get("decay", "none"), plan["max_steps"])
    clock = StepClock(device)
    step, curve, reason = 0, [], None
    state_path = folder / "state.pt"
    if state_path.is_file():
        state = torch.load(state_path, weights_only=True, map_location=device)
        model.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimiser"])
        step, clock.cpu, clock.wall = int(state["step"]), float(state["cpu"]), float(state["wall"])
        clock.gpu = float(state.get("gpu", 0.0))
        curve = [Evaluation(**e) for e in json.loads(state["curve"])]
        reason = state.get("reason") or None
        out(f"{name}: resuming at step {step}" + (f" (it had ended: {reason})" if reason else ""))

    def save() -> None:
        buffer = io.BytesIO()
        torch.save({"model": model.state_dict(), "optimiser": optimiser.state_dict(), "step": step, "cpu": clock.cpu,
                    "wall": clock.wall, "gpu": clock.gpu, "reason": reason or "",
                    "curve": json.dumps([asdict(e) for e in curve])}, buffer)
        atomic_write_bytes(state_path, buffer.getvalue())
        write_json(folder / "curve.json", [asdict(e) for e in curve])

    evaluations = [s for s in schedule(plan["first_evaluation"], plan["max_steps"]) if s > step]
    if reason is None and step >= plan["max_steps"]:  # a state saved at the cap by a version that kept no reason
        reason = "step cap"
    health = TrainingHealth()
    loss_fn = ReconstructionLoss().to(device)
    n = train_images.shape[0]
    saved_at = time.perf_counter()
    while reason is None:
        epoch, position = divmod(step, n)
        image = train_images[int(epoch_order(n, job["seed"], epoch, n)[position]), plane]
        horizontal, vertical = epoch_flips(job["seed"], epoch, [position])[0]
        dims = [d for d, flip in ((-1, horizontal), (-2, vertical)) if flip]
        amplitude = peak_normalised((image.flip(dims) if dims else image)[None, None]).to(device)
        schedule_.apply(optimiser, step)
        clock.start()
        stats = training_step(model, optimiser, setup, amplitude, loss_fn)
        clock.stop()
        step += 1
        verdict = health.update(stats)
        if verdict is not None:
            reason = verdict.split(" at step")[0]  # "stopped learning" / "diverged": `steps` says where
            out(f"{name}: {verdict}")
        if evaluations and step == evaluations[0] or reason is not None:
            evaluations = evaluations[1:] if evaluations and step == evaluations[0] else evaluations
            curve.append(Evaluation(step, round(clock.cpu, 2), round(clock.wall, 2), validation.score(model)[0],
                                    *held_out.score(model), gpu_seconds=round(clock.gpu, 2) if clock.gpu else None))
            gain = doubling_gain(curve)
            out(f"{name}: step {step}, validation {curve[-1].val_psnr:.2f} dB, held-out {curve[-1].psnr:.2f} dB"
                + (f", {gain:+.2f} dB over the last doubling" if gain is not None else ""))
            if reason is None and step >= plan["max_steps"]:
                reason = "step cap"
            elif (reason is None and math.log2(step).is_integer()
                  and flat_doublings(curve, plan["min_steps"], plan["min_gain_db"]) >= plan.get("patience", 1)):
                reason = "flat"
            save()
            saved_at = time.perf_counter()
        elif time.perf_counter() - saved_at > SAVE_EVERY_S:
            save()
            saved_at = time.perf_counter()
    done = {"name": name, "method": job["method"], "seed": job["seed"], "iris": job.get("iris", True),
            "reason": reason, "steps": step, "cpu_seconds": round(clock.cpu, 2), "wall_seconds": round(clock.wall, 2),
            "gpu_seconds": round(clock.gpu, 2) if clock.gpu else None, "device": str(device),
            "curve": [asdict(e) for e in curve], "per_image": held_out.score_each(model),
            "inference_seconds": inference_seconds(model, held_out.inputs[0], repeats=5)}
    write_json(folder / "done.json", done)
    return done


if __name__ == "__main__":
    run_job(Path(sys.argv[1]), sys.argv[2], out=lambda line: print(line, flush=True))
