"""The report of a `bench reproduce` run: the table beside the paper's figures, the paper's comparisons one by
one, the curves and the plots, built from whatever jobs of the run have finished.

Per method (and bench variant), over its seeds (mean +- sample standard deviation): the held-out score where
training ended and where its validation score was best (the checkpoint early stopping would keep: batch-1
Adam at a constant learning rate wanders by a fraction of a dB from step to step), and two readings that
compare methods at one budget: at equal steps (the fewest steps any
seed of the family's baseline network trained) and at equal time (the mean training CPU time of the
baseline's seeds); each reading is the last evaluation at or before that budget.
"""

from __future__ import annotations

import io
import json
import statistics
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from benchctl.benchmarks.learned import BASELINES, with_baselines
from benchctl.benchmarks.reproduce_job import VALIDATION_COUNT, VALIDATION_FIRST, bench_for, read_done, read_progress
from benchctl.cgh.learned.models import VARIANTS
from benchctl.files import atomic_write_bytes, write_csv, write_json
from benchctl.holograms.scene import compute_scene
from benchctl.targets import load_target, photo_specs, prepare_target

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

COMPARISONS = (
    ("holonet-dcm2", "holonet", True, "x2 about equal to HoloNet"),
    ("holonet-dcm4", "holonet", True, "x4 1-2 dB below HoloNet"),
    ("holonet-pyramid", "holonet-dcm4", True, "the pyramid recovers x4's loss"),
    ("holonet-ps2", "holonet-dcm2", True, "SR -> PixelShuffle costs about 1 dB at x2"),
    ("holonet-ps4", "holonet-dcm4", True, "SR -> PixelShuffle costs about 0.5 dB at x4"),
    ("holonet-lowdef2", "holonet-dcm2", True, "propagating at low definition collapses quality"),
    ("holonet-lowdef2", "holonet-dcm2", False, "the same, on the bench without its iris"),
    ("holonet-dcm2-nolfm", "holonet-dcm2", True, "LFM -> None costs 0.75 dB"),
    ("holonet-dcm2-noeccm", "holonet-dcm2", True, "ECCM -> None costs 0.48 dB"),
    ("holonet-dcm2-nogrn", "holonet-dcm2", True, "GRN -> None costs 0.7 dB"),
    ("ccnn-dcm4", "ccnn", True, "CCNN x4 about equal to CCNN"),
)
"""The paper's claims as (method, reference, with the iris, claim): each is read as the method's mean minus the
reference's, next to the paper's difference (on the paper's bench, which has no iris at 1088 rows)."""


def _label(method: str, iris: bool) -> str:
    return method if iris else f"{method} (no iris)"


def _reading(curve: Sequence[dict[str, Any]], key: str, budget: float) -> dict[str, Any]:
    """The last evaluation at or before `budget` of `key` (the first one if none is)."""
    before = [e for e in curve if e[key] <= budget]
    return before[-1] if before else curve[0]


def _spread(values: Sequence[float]) -> tuple[float, float]:
    return statistics.mean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def collect(run_dir: Path) -> tuple[dict[str, Any], dict[tuple[str, bool], list[dict[str, Any]]], list[str]]:
    """The plan, the finished jobs grouped by (method, iris) in plan order, and the names of unfinished jobs."""
    plan = json.loads((Path(run_dir) / "plan.json").read_text())
    groups: dict[tuple[str, bool], list[dict[str, Any]]] = {}
    unfinished = []
    for job in plan["jobs"]:
        done = read_done(run_dir, job["name"])
        if done is None or not done["curve"]:
            unfinished.append(job["name"])
            continue
        groups.setdefault((job["method"], job["iris"]), []).append(done)
    return plan, groups, unfinished


def budgets(groups: dict[tuple[str, bool], list[dict[str, Any]]]) -> dict[str, tuple[int, float]]:
    """Per family, (equal steps, equal CPU seconds): the baseline's fewest steps and mean CPU time (over all
    finished jobs where the baseline has none)."""
    result = {}
    everyone = [d for runs in groups.values() for d in runs]
    for family, base in BASELINES.items():
        runs = groups.get((base, True)) or [d for d in everyone if VARIANTS[d["method"]].family == family]
        if runs:
            result[family] = (min(d["steps"] for d in runs), statistics.mean(d["cpu_seconds"] for d in runs))
    return result


def table_rows(groups: dict[tuple[str, bool], list[dict[str, Any]]], memory: dict[str, float]) -> list[dict[str, Any]]:
    """One row per (method, iris): seeds, what ended training, scores with their spread, ratios to the baseline."""
    equal = budgets(groups)
    rows: list[dict[str, Any]] = []
    for (method, iris), runs in groups.items():
        family = VARIANTS[method].family
        steps_budget, time_budget = equal[family]
        finals = [d["curve"][-1] for d in runs]
        at_steps = [_reading(d["curve"], "step", steps_budget) for d in runs]
        at_time = [_reading(d["curve"], "cpu_seconds", time_budget) for d in runs]
        paper = PAPER.get(method)
        row: dict[str, Any] = {
            "method": _label(method, iris), "family": family, "iris": iris, "seeds": len(runs),
            "seed_list": " ".join(str(d["seed"]) for d in runs),
            "ended_by": ", ".join(sorted({d["reason"] for d in runs})),
            "steps": round(statistics.mean(d["steps"] for d in runs)),
            "cpu_minutes": round(statistics.mean(d["cpu_seconds"] for d in runs) / 60, 2),
            "psnr_db": _spread([e["psnr"] for e in finals]), "ssim": statistics.mean(e["ssim"] for e in finals),
            "best_val_psnr_db": _spread([_best(d) for d in runs]),
            "equal_steps": steps_budget, "steps_psnr_db": _spread([e["psnr"] for e in at_steps]),
            "equal_cpu_seconds": round(time_budget, 1), "time_psnr_db": _spread([e["psnr"] for e in at_time]),
            "paper_psnr_db": paper[0] if paper else None, "paper_ssim": paper[1] if paper else None,
            "paper_table": paper[2] if paper else "",
            "inference_seconds": statistics.median(d["inference_seconds"] for d in runs),
            "train_step_peak_mib": memory.get(method),
        }
        rows.append(row)
    for row, base in with_baselines(rows):
        for key in ("psnr_db", "best_val_psnr_db", "steps_psnr_db", "time_psnr_db"):
            row[key.replace("psnr_db", "delta_db")] = row[key][0] - base[key][0]
        row["speedup"] = base["inference_seconds"] / row["inference_seconds"]
        if row["train_step_peak_mib"] and base["train_step_peak_mib"]:
            row["memory_ratio"] = row["train_step_peak_mib"] / base["train_step_peak_mib"]
        paper, paper_base = PAPER.get(row["method"]), PAPER.get(base["method"])
        if paper and paper_base and row["iris"]:
            row["paper_delta_db"] = paper[0] - paper_base[0]
    return rows


def _best(run: dict[str, Any]) -> float:
    """The held-out score where the run's validation score was best (the checkpoint early stopping would keep)."""
    return float(max(run["curve"], key=lambda e: e["val_psnr"])["psnr"])


def _end(run: dict[str, Any]) -> float:
    return float(run["curve"][-1]["psnr"])


def comparisons(groups: dict[tuple[str, bool], list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Each of the paper's claims that this run can read: here (mean difference where training ended, and where
    validation was best; where both have the same seeds, the spread of the per-seed differences at the end) against
    the paper's difference."""
    result = []
    for method, reference, iris, claim in COMPARISONS:
        mine, theirs = groups.get((method, iris)), groups.get((reference, iris))
        if not mine or not theirs:
            continue
        by_seed = {d["seed"]: _end(d) for d in theirs}
        paired = [_end(d) - by_seed[d["seed"]] for d in mine if d["seed"] in by_seed]
        result.append({"claim": claim, "method": _label(method, iris), "reference": _label(reference, iris),
                       "here_db": statistics.mean(map(_end, mine)) - statistics.mean(map(_end, theirs)),
                       "best_val_db": statistics.mean(map(_best, mine)) - statistics.mean(map(_best, theirs)),
                       "paired_sd_db": statistics.stdev(paired) if len(paired) > 1 else None,
                       "pairs": len(paired), "paper_db": PAPER[method][0] - PAPER[reference][0]})
    return result


def _pm(value: tuple[float, float], seeds: int) -> str:
    return f"{value[0]:.2f} +- {value[1]:.2f}" if seeds > 1 else f"{value[0]:.2f}"


def format_table(rows: Sequence[dict[str, Any]], dpac: tuple[float, float] | None) -> list[str]:
    """The Markdown table: where training ended, at equal steps and equal time, the paper, memory and speed."""
    def num(row: dict[str, Any], key: str, fmt: str) -> str:
        value = row.get(key)
        return "-" if value is None else format(value, fmt)

    lines = ["| method | seeds | ended by | steps | CPU-min | PSNR (dB), end | SSIM | vs base | at best validation | "
             "vs base | PSNR at equal steps "
             "| vs base | PSNR at equal time | vs base | paper PSNR / SSIM | paper vs base | train-step MiB | "
             "x base memory | s / frame | speed-up |",
             "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- "
             "| ---: | ---: "
             "| ---: | ---: | ---: |"]
    for r in rows:
        paper = (f"{r['paper_psnr_db']:.2f} / {r['paper_ssim']:.3f} ({r['paper_table']})"
                 if r["paper_psnr_db"] is not None and r["iris"] else "-")
        lines.append(
            f"| {r['method']} | {r['seeds']} | {r['ended_by']} | {r['steps']} | {r['cpu_minutes']:.1f} | "
            f"{_pm(r['psnr_db'], r['seeds'])} | {r['ssim']:.3f} | {num(r, 'delta_db', '+.2f')} | "
            f"{_pm(r['best_val_psnr_db'], r['seeds'])} | {num(r, 'best_val_delta_db', '+.2f')} | "
            f"{_pm(r['steps_psnr_db'], r['seeds'])} ({r['equal_steps']}) | {num(r, 'steps_delta_db', '+.2f')} | "
            f"{_pm(r['time_psnr_db'], r['seeds'])} ({r['equal_cpu_seconds'] / 60:.1f} min) | "
            f"{num(r, 'time_delta_db', '+.2f')} | {paper} | {num(r, 'paper_delta_db', '+.2f')} | "
            f"{num(r, 'train_step_peak_mib', '.0f')} | {num(r, 'memory_ratio', '.2f')} | "
            f"{r['inference_seconds']:.4f} | {num(r, 'speedup', '.2f')} |")
    if dpac is not None:
        lines.append(f"| dpac (classical reference) | - | - | - | - | {dpac[0]:.2f} | {dpac[1]:.3f} | - | - | - | - | "
                     "- | - | - | - | - | - | - | - | - |")
    return lines


def format_comparisons(found: Sequence[dict[str, Any]]) -> list[str]:
    lines = ["| the paper's claim | method - reference | here (dB), end | spread of paired seeds (dB) | "
             "here (dB), at best validation | paper (dB) |",
             "| --- | --- | ---: | ---: | ---: | ---: |"]
    for c in found:
        spread = f"{c['paired_sd_db']:.2f} ({c['pairs']} seeds)" if c["paired_sd_db"] is not None else "-"
        lines.append(f"| {c['claim']} | {c['method']} - {c['reference']} | {c['here_db']:+.2f} | {spread} | "
                     f"{c['best_val_db']:+.2f} | {c['paper_db']:+.2f} |")
    return lines


def dpac_reference(run_dir: Path, plan: dict[str, Any]) -> tuple[float, float]:
    """DPAC's mean amplitude PSNR / SSIM on the held-out photographs on the run's bench (kept in dpac.json)."""
    path = Path(run_dir) / "dpac.json"
    if path.is_file():
        saved = json.loads(path.read_text())
        return saved["psnr_db"], saved["ssim"]
    bench = bench_for(plan, {"iris": True})
    grid, roi = bench.section("slm").shape, bench.section("optics").roi
    psnrs, ssims = [], []
    for spec in photo_specs("eval"):
        scene = compute_scene(prepare_target(load_target(spec, size=roi), grid, roi), bench, "dpac",
                              colours=[plan["colour"]])
        psnrs += [c.scores["psnr_amplitude_db"] for c in scene.colours if not c.skipped]
        ssims += [c.scores["ssim_amplitude"] for c in scene.colours if not c.skipped]
    write_json(path, {"psnr_db": statistics.mean(psnrs), "ssim": statistics.mean(ssims)})
    return statistics.mean(psnrs), statistics.mean(ssims)


def write_report(run_dir: Path, out: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """reproduction.md / .csv, comparisons.csv, curves.csv and the plots from the finished jobs; the rows."""
    run_dir = Path(run_dir)
    plan, groups, unfinished = collect(run_dir)
    memory_path = run_dir / "memory.json"
    memory = json.loads(memory_path.read_text()) if memory_path.is_file() else {}
    dpac = dpac_reference(run_dir, plan)
    rows = table_rows(groups, memory) if groups else []
    found = comparisons(groups)
    lines = format_table(rows, dpac)
    size = plan["size"]
    header = [f"Command: `{plan['command']}`" if plan.get("command") else "",
              f"Bench: {size[0]}x{size[1]} (Fresnel-scaled), {plan['colour']}; data {plan['data']}; validation "
              f"(stopping rule): procedural images {VALIDATION_FIRST}-{VALIDATION_FIRST + VALIDATION_COUNT - 1}; "
              f"scores: held-out photographs {', '.join(photo_specs('eval'))}, mean over them; Adam lr "
              f"{plan['lr']:g}; stop: < {plan['min_gain_db']:g} dB per doubling of steps at "
              f"{plan.get('patience', 1)} power-of-two step(s) in a row from step {plan['min_steps']} on, cap "
              f"{plan['max_steps']} steps; {plan['threads']} torch thread(s) per job.",
              f"Change of plan: {plan['rule_change']}." if plan.get("rule_change") else "",
              f"Unfinished jobs (not in the table): {', '.join(unfinished)}." if unfinished else "", ""]
    for line in lines + [""] + format_comparisons(found):
        out(line)
    rows_csv = [{k: (f"{v[0]:.3f}" if isinstance(v, tuple) else v) for k, v in r.items()}
                | {f"{k}_sd": f"{v[1]:.3f}" for k, v in r.items() if isinstance(v, tuple)} for r in rows]
    written = [write_csv(run_dir / "reproduction.csv", rows_csv), write_csv(run_dir / "comparisons.csv", found),
               write_csv(run_dir / "curves.csv", _curves(plan, run_dir))]
    text = "\n".join(header + lines + ["", *format_comparisons(found)]) + "\n"
    written.append(atomic_write_bytes(run_dir / "reproduction.md", text.encode()))
    for key, label, name in (("step", "training step", "psnr_vs_step.png"),
                             ("cpu_seconds", "training CPU seconds", "psnr_vs_seconds.png")):
        plot = _plot(groups, key, label, run_dir / name, dpac[0])
        if plot is not None:
            written.append(plot)
    out("wrote " + ", ".join(str(p) for p in written))
    return rows


def _curves(plan: dict[str, Any], run_dir: Path) -> list[dict[str, Any]]:
    rows = []
    for job in plan["jobs"]:
        done = read_done(run_dir, job["name"])
        for e in done["curve"] if done else read_progress(run_dir, job["name"]):
            rows.append({"job": job["name"], "method": job["method"], "seed": job["seed"], "iris": job["iris"],
                         "finished": done is not None} | e)
    return rows


def seed_curve(runs: Sequence[dict[str, Any]], key: str) -> tuple[list[float], list[list[float]], int]:
    """One method's curve over its seeds: at each evaluation the mean of `key` (step or CPU seconds) and the held-out
    PSNRs of the seeds that reached it, so a seed that stopped early (a stall, the stopping rule) leaves the curve
    to the others instead of cutting it short; and how many seeds stopped before the longest."""
    length = max(len(d["curve"]) for d in runs)
    going = [[d for d in runs if len(d["curve"]) > i] for i in range(length)]
    x = [statistics.mean(d["curve"][i][key] for d in present) for i, present in enumerate(going)]
    return x, [[d["curve"][i]["psnr"] for d in present] for i, present in enumerate(going)], len(runs) - len(going[-1])


def _plot(groups: dict[tuple[str, bool], list[dict[str, Any]]], key: str, label: str, path: Path,
          dpac: float) -> Path | None:
    """Held-out PSNR against step or CPU seconds (log axis): the mean over seeds, the seeds' range shaded."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    fig, ax = plt.subplots(figsize=(9, 5.5))
    for (method, iris), runs in groups.items():
        x, values, stopped = seed_curve(runs, key)
        style = "--" if VARIANTS[method].family == "ccnn" else ":" if not iris else "-"
        line, = ax.plot(x, [statistics.mean(v) for v in values], style, marker="o", markersize=2.5,
                        label=f"{_label(method, iris)} ({len(runs)}"
                        + (f", {stopped} stopped early)" if stopped else ")"))
        if len(runs) > 1:
            ax.fill_between(x, [min(v) for v in values], [max(v) for v in values], color=line.get_color(), alpha=0.15)
    ax.axhline(dpac, color="black", linewidth=0.8, linestyle="-.", label="DPAC")
    ax.set_xscale("log", base=2)
    ax.set_xlabel(label)
    ax.set_ylabel("PSNR, amplitude, held-out photographs (dB)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return atomic_write_bytes(path, buffer.getvalue())
