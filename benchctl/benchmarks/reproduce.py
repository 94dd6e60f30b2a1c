"""`benchctl bench reproduce`: the quality side of the DCM paper (its Tables 1, 2 and 4) at a CPU-trainable scale.

Every method trains from the same seed on the same images in the same order (the `benchctl train` recipe:
seeded epoch order and flips, Adam, MSE on the ROI after the least-squares scale), one colour, on a bench
scaled like `bench speed-vs-error` does (pitch kept, distance scaled with the grid's area so that the
Fresnel number stays the paper's). Each method gets the same budget: `cpu_seconds` of training or `steps`
optimisation steps. Time is this process's CPU time in the training steps (all its threads; evaluation
excluded), not the wall clock: on a machine shared with other work the wall clock charges a method for the
others' load, CPU time does not (with one thread and an idle core the two agree; `threads` sets torch's). It
is evaluated on the held-out photographs (`photo_specs("eval")`, never trained on) at `evaluations` even
intervals of its budget, scored exactly as `benchctl generate` scores a hologram: 8-bit displayed phase
through the SLM's lookup table, amplitude PSNR / SSIM on the ROI after the least-squares scale.

One timed run gives both of the issue's budgets: "equal time" is each method's score at the end of its
`cpu_seconds`; "equal steps" is its score at the step count the first method reached in that time (put the
slowest method first: holonet, which runs its U-Nets at full definition); a method that did not reach that
step count is read at its last step, and the table shows the step count read. Next to the scores: the
paper's figure for the same network, the difference to the family's baseline network here and in the paper,
the peak memory of one training step (a fresh subprocess per model, as `bench learned` measures it) and the
inference time per frame, as ratios to the baseline too. DPAC on the same photographs is the classical
reference. Writes curves.csv, reproduction.csv, reproduction.md and the plots psnr_vs_step.png and
psnr_vs_seconds.png.
"""

from __future__ import annotations

import io
import shlex
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from benchctl.benchmarks.learned import inference_seconds, measure_training_step
from benchctl.benchmarks.speed_vs_error import resized_profile
from benchctl.cgh import OpticalSetup
from benchctl.cgh.learned import LEARNED_METHODS, build_model
from benchctl.cgh.learned.models import VARIANTS
from benchctl.runner.learned.data import image_sources
from benchctl.runner.learned.training import (
    ReconstructionLoss,
    epoch_flips,
    epoch_order,
    load_targets,
    peak_normalised,
    training_step,
)
from benchctl.devices.slm import slm_for
from benchctl.errors import BadValueError
from benchctl.files import atomic_write_bytes, ensure_dir, write_csv
from benchctl.optics import amplitude_scores, crop_roi, lsq_scale
from benchctl.profiles import Profile
from benchctl.runner.holograms import compute_scene
from benchctl.runner.setups import optical_setup
from benchctl.targets import load_target, photo_specs, prepare_target, target_plane

DEFAULT_METHODS = ("holonet", "holonet-dcm2", "holonet-dcm4", "holonet-pyramid", "holonet-ps2", "holonet-ps4",
                   "holonet-lowdef2", "holonet-dcm2-nolfm", "holonet-dcm2-noeccm", "holonet-dcm2-nogrn", "ccnn",
                   "ccnn-dcm4")
DEFAULT_SIZE = (272, 480)
DEFAULT_DATA = "procedural:32+photos:train"
BASELINES = {"holonet": "holonet", "ccnn": "ccnn"}

PAPER: dict[str, tuple[float, float, str]] = {
    "holonet": (30.47, 0.9257, "T4"),
    "holonet-dcm2": (30.83, 0.9312, "T4"),
    "holonet-dcm4": (29.04, 0.9139, "T4"),
    "holonet-pyramid": (30.51, 0.93, "T1"),
    "holonet-ps2": (29.83, 0.9165, "T4"),
    "holonet-ps4": (28.55, 0.9007, "T4"),
    "holonet-lowdef2": (16.63, 0.4893, "T4"),
    "holonet-dcm2-nolfm": (30.08, 0.9147, "T4"),
    "holonet-dcm2-noeccm": (30.35, 0.9167, "T4"),
    "holonet-dcm2-nogrn": (30.13, 0.9085, "T4"),
    "ccnn": (42.06, 0.97, "T2"),
    "ccnn-dcm4": (42.94, 0.98, "T2"),
}
"""The paper's PSNR (dB) / SSIM per network: Table 4 (1080p, red, DIV2K-val) for HoloNet and its ablations,
Table 1 (1080p) for the pyramid, Table 2 (4K) for CCNN-CGH, which the paper does not train at 1080p."""


@dataclass
class Evaluation:
    """A score on the held-out photographs at one point of training."""

    step: int
    cpu_seconds: float  # this process's CPU time in training steps so far (all threads; the budget's clock)
    wall_seconds: float  # wall-clock time in training steps so far
    psnr: float
    ssim: float


@dataclass
class MethodRun:
    """One method's training run: its curve, and the readings at equal time and equal steps."""

    method: str
    curve: list[Evaluation] = field(default_factory=list)
    equal_steps: Evaluation | None = None
    measures: dict[str, Any] = field(default_factory=dict)

    @property
    def final(self) -> Evaluation:
        return self.curve[-1]


class HeldOut:
    """The held-out photographs on the bench for one colour, scored like `benchctl generate` scores them."""

    def __init__(self, bench: Profile, colour: str, targets: Sequence[str]) -> None:
        channel = bench.channel(colour)
        self.name = channel.name
        self.setup = optical_setup(bench, channel.name)
        self.slm = slm_for(bench)
        plane = target_plane(channel)
        grid, roi = self.setup.shape, self.setup.roi
        planes = [prepare_target(load_target(t, size=roi), grid, roi)[plane] for t in targets]
        self.inputs = [peak_normalised(p[None, None]) for p in planes]
        self.targets = [crop_roi(p, roi) for p in planes]

    def score(self, model: torch.nn.Module) -> tuple[float, float]:
        """Mean amplitude PSNR (dB) and SSIM of `model`'s 8-bit displayed holograms over the photographs."""
        model.eval()
        psnrs, ssims = [], []
        with torch.no_grad():
            for amplitude, target in zip(self.inputs, self.targets):
                gray = self.slm.encode(model(amplitude)[0, 0], self.name)
                recon = self.setup.reconstruct_roi(torch.from_numpy(self.slm.decode(gray, self.name)))
                scores = amplitude_scores(recon * lsq_scale(recon, target), target)
                psnrs.append(scores["psnr_amplitude_db"])
                ssims.append(scores["ssim_amplitude"])
        return statistics.mean(psnrs), statistics.mean(ssims)


def _check(methods: Sequence[str], seconds: float | None, steps: int | None, evaluations: int,
           threads: int | None) -> None:
    unknown = [m for m in methods if m not in LEARNED_METHODS]
    if unknown:
        raise BadValueError(f"--methods: unknown learned method(s) {', '.join(unknown)}; known: "
                            f"{', '.join(LEARNED_METHODS)}")
    if not methods:
        raise BadValueError("--methods: give at least one learned method")
    if (seconds is None) == (steps is None):
        raise BadValueError("give one budget: --minutes M (training time per method) or --steps N")
    if seconds is not None and not seconds > 0:
        raise BadValueError(f"--minutes must be > 0, got {seconds / 60:g}")
    if steps is not None and steps < 1:
        raise BadValueError(f"--steps must be >= 1, got {steps}")
    if evaluations < 1:
        raise BadValueError(f"--evaluations must be >= 1, got {evaluations}")
    if threads is not None and threads < 1:
        raise BadValueError(f"--threads must be >= 1, got {threads}")


def train_and_evaluate(method: str, setup: OpticalSetup, plane: int, train_images: torch.Tensor,
                       held_out: HeldOut, *, cpu_seconds: float | None, steps: int | None, evaluations: int,
                       equal_step: int | None, lr: float, seed: int) -> tuple[MethodRun, torch.nn.Module]:
    """Train `method` from `seed` for the budget (`cpu_seconds` of training or `steps`), evaluating on
    `held_out` at `evaluations` even intervals of the budget and at step `equal_step` if it gets there."""
    torch.manual_seed(seed)
    model = build_model(method, setup)
    optimiser = torch.optim.Adam(model.parameters(), lr=lr, betas=(0.9, 0.999))
    loss_fn = ReconstructionLoss()
    run = MethodRun(method)
    n = train_images.shape[0]
    step, clock, cpu, mark = 0, 0.0, 0.0, 1

    def evaluate() -> Evaluation:
        return Evaluation(step, round(cpu, 3), round(clock, 3), *held_out.score(model))

    while True:
        epoch, position = divmod(step, n)
        image = train_images[int(epoch_order(n, seed, epoch, n)[position]), plane]
        horizontal, vertical = epoch_flips(seed, epoch, [position])[0]
        dims = [d for d, flip in ((-1, horizontal), (-2, vertical)) if flip]
        amplitude = peak_normalised((image.flip(dims) if dims else image)[None, None])
        start, start_cpu = time.perf_counter(), time.process_time()
        training_step(model, optimiser, setup, amplitude, loss_fn)
        clock += time.perf_counter() - start
        cpu += time.process_time() - start_cpu
        step += 1
        progress = cpu / cpu_seconds if cpu_seconds is not None else step / steps  # type: ignore[operator]
        done = progress >= 1.0
        if step == equal_step:
            run.equal_steps = evaluate()
        if done or progress >= mark / evaluations:
            run.curve.append(run.equal_steps if run.equal_steps and run.equal_steps.step == step else evaluate())
            mark = int(progress * evaluations) + 1
        if done:
            return run, model


def run_reproduction(
    profile: Profile,
    *,
    size: tuple[int, int] = DEFAULT_SIZE,
    cpu_seconds: float | None = None,
    steps: int | None = None,
    methods: Sequence[str] = DEFAULT_METHODS,
    colour: str = "red",
    data: str = DEFAULT_DATA,
    evaluations: int = 6,
    lr: float = 1e-3,
    seed: int = 42,
    memory: bool = True,
    threads: int | None = None,
    out_dir: Path | None = None,
    command: str | None = None,
    out: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """Train and evaluate each method with the same data, seed and budget (see the module doc); print the
    table and, with `out_dir`, write the CSVs, the report and the plots. Returns the table's rows."""
    methods = list(dict.fromkeys(methods))
    _check(methods, cpu_seconds, steps, evaluations, threads)
    previous_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        return _reproduce(profile, size, cpu_seconds, steps, methods, colour, data, evaluations, lr, seed, memory,
                          out_dir, command, out)
    finally:
        torch.set_num_threads(previous_threads)


def _reproduce(profile: Profile, size: tuple[int, int], cpu_seconds: float | None, steps: int | None,
               methods: list[str], colour: str, data: str, evaluations: int, lr: float, seed: int, memory: bool,
               out_dir: Path | None, command: str | None, out: Callable[[str], None]) -> list[dict[str, Any]]:
    started = time.perf_counter()
    bench = resized_profile(profile, size)
    channel = bench.channel(colour)
    setup = optical_setup(bench, channel.name)
    held_out = HeldOut(bench, channel.name, photo_specs("eval"))
    train_images = load_targets(image_sources(data), setup.shape, setup.roi)
    plane = target_plane(channel)
    budget = (f"{cpu_seconds / 60:g} CPU-min of training per method" if cpu_seconds is not None
              else f"{steps} steps per method") + f", {torch.get_num_threads()} torch thread(s)"
    out(f"grid {setup.shape[0]}x{setup.shape[1]}, ROI {setup.roi[0]}x{setup.roi[1]}, {channel.name} "
        f"{channel.wavelength_nm:g} nm, pitch {bench.slm.pitch_um:g} um, distance "  # type: ignore[union-attr]
        f"{bench.optics.distance_mm:.4g} mm (Fresnel number of the full bench); {len(train_images)} training "  # type: ignore[union-attr]
        f"images ({data}); evaluation on {', '.join(photo_specs('eval'))}; {budget}; seed {seed}, lr {lr:g}")
    dpac = _dpac_scores(bench, channel.name)
    out(f"DPAC on the held-out photographs: {dpac[0]:.2f} dB / {dpac[1]:.3f}")
    runs: list[MethodRun] = []
    equal_step: int | None = None
    for method in methods:
        run, model = train_and_evaluate(method, setup, plane, train_images, held_out, cpu_seconds=cpu_seconds,
                                        steps=steps, evaluations=evaluations, equal_step=equal_step, lr=lr, seed=seed)
        equal_step = equal_step or run.final.step
        run.measures["inference_seconds"] = inference_seconds(model, held_out.inputs[0], repeats=3)
        if memory:
            run.measures["train_step_peak_mib"] = measure_training_step(method, setup, torch.device("cpu"))[
                "peak_bytes"] / 2**20
        runs.append(run)
        out(f"  {method}: {run.final.step} steps in {run.final.cpu_seconds:.0f} CPU-s ({run.final.wall_seconds:.0f} s "
            f"wall), {run.final.psnr:.2f} dB / "
            f"{run.final.ssim:.3f} on the held-out photographs")
    rows = _rows(runs)
    wall = time.perf_counter() - started
    lines = format_table(rows, dpac)
    for line in lines:
        out(line)
    out(f"wall time {wall / 60:.1f} min")
    if out_dir is not None:
        folder = ensure_dir(Path(out_dir))
        curves = [{"method": r.method, "step": e.step, "cpu_seconds": e.cpu_seconds, "wall_seconds": e.wall_seconds,
                   "psnr_amplitude_db": round(e.psnr, 3), "ssim_amplitude": round(e.ssim, 4)}
                  for r in runs for e in r.curve]
        written = [write_csv(folder / "curves.csv", curves), write_csv(folder / "reproduction.csv", rows)]
        header = [f"Command: `{command}`" if command else "", f"Bench: {setup.shape[0]}x{setup.shape[1]}, ROI "
                  f"{setup.roi[0]}x{setup.roi[1]}, {channel.name} {channel.wavelength_nm:g} nm; {budget}; seed "
                  f"{seed}; data {data}; wall time {wall / 60:.1f} min.", ""]
        written.append(atomic_write_bytes(folder / "reproduction.md", ("\n".join(header + lines) + "\n").encode()))
        for key, label, name in (("step", "training step", "psnr_vs_step.png"),
                                 ("cpu_seconds", "training CPU seconds", "psnr_vs_seconds.png")):
            plot = _plot(runs, key, label, folder / name)
            if plot is not None:
                written.append(plot)
        out("wrote " + ", ".join(str(p) for p in written))
    return rows


def _dpac_scores(bench: Profile, colour: str) -> tuple[float, float]:
    grid, roi = bench.slm.shape, bench.optics.roi  # type: ignore[union-attr]
    psnrs, ssims = [], []
    for spec in photo_specs("eval"):
        scene = compute_scene(prepare_target(load_target(spec, size=roi), grid, roi), bench, "dpac", colours=[colour])
        psnrs += [c.scores["psnr_amplitude_db"] for c in scene.colours if not c.skipped]
        ssims += [c.scores["ssim_amplitude"] for c in scene.colours if not c.skipped]
    return statistics.mean(psnrs), statistics.mean(ssims)


def _rows(runs: Sequence[MethodRun]) -> list[dict[str, Any]]:
    by_name = {r.method: r for r in runs}
    rows = []
    for run in runs:
        paper = PAPER.get(run.method)
        steps_reading = run.equal_steps or run.final
        row: dict[str, Any] = {
            "method": run.method, "paper_table": paper[2] if paper else "",
            "paper_psnr_db": paper[0] if paper else "", "paper_ssim": paper[1] if paper else "",
            "steps": run.final.step, "cpu_seconds": run.final.cpu_seconds, "wall_seconds": run.final.wall_seconds,
            "time_psnr_db": round(run.final.psnr, 3), "time_ssim": round(run.final.ssim, 4),
            "equal_steps": steps_reading.step, "steps_psnr_db": round(steps_reading.psnr, 3),
            "steps_ssim": round(steps_reading.ssim, 4),
            "inference_seconds": run.measures["inference_seconds"],
            "train_step_peak_mib": run.measures.get("train_step_peak_mib", ""),
        }
        base_name = BASELINES[VARIANTS[run.method].family]
        base = by_name.get(base_name)
        if base is not None:
            base_steps = base.equal_steps or base.final
            row |= {"baseline": base_name, "time_delta_db": round(run.final.psnr - base.final.psnr, 3),
                    "steps_delta_db": round(steps_reading.psnr - base_steps.psnr, 3),
                    "paper_delta_db": round(paper[0] - PAPER[base_name][0], 2) if paper else "",
                    "speedup": base.measures["inference_seconds"] / run.measures["inference_seconds"]}
            if row["train_step_peak_mib"] != "" and base.measures.get("train_step_peak_mib"):
                row["memory_ratio"] = row["train_step_peak_mib"] / base.measures["train_step_peak_mib"]
        rows.append(row)
    return rows


def format_table(rows: Sequence[dict[str, Any]], dpac: tuple[float, float]) -> list[str]:
    """The report's Markdown table: paper vs here at equal time and equal steps, memory and speed ratios."""
    def num(row: dict[str, Any], key: str, fmt: str) -> str:
        value = row.get(key, "")
        return "-" if value == "" else format(value, fmt)

    lines = ["| method | paper PSNR / SSIM | paper vs base (dB) | steps | PSNR / SSIM, equal time | vs base (dB) | "
             "at step | PSNR / SSIM, equal steps | vs base (dB) | train-step MiB | x base memory | s / frame | "
             "speed-up |",
             "| --- | --- | ---: | ---: | --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        paper = f"{r['paper_psnr_db']:.2f} / {r['paper_ssim']:.3f} ({r['paper_table']})" if r["paper_psnr_db"] != "" \
            else "-"
        lines.append(
            f"| {r['method']} | {paper} | {num(r, 'paper_delta_db', '+.2f')} | {r['steps']} | "
            f"{r['time_psnr_db']:.2f} / {r['time_ssim']:.3f} | {num(r, 'time_delta_db', '+.2f')} | "
            f"{r['equal_steps']} | {r['steps_psnr_db']:.2f} / {r['steps_ssim']:.3f} | "
            f"{num(r, 'steps_delta_db', '+.2f')} | {num(r, 'train_step_peak_mib', '.0f')} | "
            f"{num(r, 'memory_ratio', '.2f')} | {r['inference_seconds']:.4f} | {num(r, 'speedup', '.2f')} |")
    lines.append(f"| dpac (classical reference) | - | - | - | {dpac[0]:.2f} / {dpac[1]:.3f} "
                 "| - | - | - | - | - | - | - | - |")
    return lines


def _plot(runs: Sequence[MethodRun], key: str, label: str, path: Path) -> Path | None:
    """Held-out PSNR against training step or seconds, one curve per method; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig, ax = plt.subplots(figsize=(8, 5))
    for run in runs:
        ax.plot([getattr(e, key) for e in run.curve], [e.psnr for e in run.curve], marker="o", markersize=3,
                label=run.method, linestyle="--" if VARIANTS[run.method].family == "ccnn" else "-")
    ax.set_xlabel(label)
    ax.set_ylabel("PSNR, amplitude, held-out photographs (dB)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return atomic_write_bytes(path, buffer.getvalue())


def reproduce_command(profile: str | None, size: tuple[int, int], minutes: float | None, steps: int | None,
                      methods: Sequence[str], colour: str, data: str, evaluations: int, lr: float, seed: int,
                      threads: int | None, out_dir: Path | None) -> str:
    """The `benchctl bench reproduce` command line that asks for exactly these settings."""
    words = ["benchctl", "bench", "reproduce", *(["--profile", profile] if profile else []),
             "--size", f"{size[0]}x{size[1]}"]
    words += ["--minutes", f"{minutes:g}"] if minutes is not None else ["--steps", str(steps)]
    words += ["--methods", ",".join(methods), "--colour", colour, "--data", data, "--evaluations", str(evaluations),
              "--lr", f"{lr:g}", "--seed", str(seed)] + (["--threads", str(threads)] if threads else [])
    return shlex.join(words + (["--out", str(out_dir)] if out_dir is not None else []))
