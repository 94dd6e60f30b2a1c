"""The report of a `bench reproduce` run: the table beside the paper's figures, the paper's comparisons one by
one, the curves and the plots, built from whatever jobs of the run have finished.

Per method (and bench variant), over its seeds (mean +- sample standard deviation): the held-out score where
training ended and where its validation score was best (the checkpoint early stopping would keep: batch-1
Adam at a constant learning rate wanders by a fraction of a dB from step to step), and two readings that
compare methods at one budget: at equal steps (the fewest steps any
seed of the family's baseline network trained) and at equal time (the mean training time of the baseline's
seeds: CPU time, or synchronised GPU time on a GPU); each reading is the last evaluation at or before that budget,
marked where the job had already ended before it (its last score, not a score at that time).

Each of the paper's claims is read as differences paired by seed (the method minus its reference trained with
the same seed), their mean with a 95 % t-interval over the pairs, and a verdict by one rule (VERDICT_RULE).
Per-image scores come from the jobs' records (runs from before they were recorded have none). A run folder whose
jobs are gone can be reported from its CSVs (curves.csv, reproduction.csv, plan.json): the curves are all there.
"""

from __future__ import annotations

import io
import json
import statistics
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from benchctl.benchmarks.learned import BASELINES, with_baselines
from benchctl.benchmarks.reproduce_job import (
    DEFAULT_HELD_OUT,
    VALIDATION_COUNT,
    VALIDATION_FIRST,
    bench_for,
    read_done,
    read_plan,
    read_progress,
)
from benchctl.calibration.calibrated import Calibrated
from benchctl.cgh.learned.models import VARIANTS
from benchctl.files import atomic_write_bytes, write_csv, write_json
from benchctl.holograms.scene import compute_scene
from benchctl.targets import prepare_target
from benchctl.training.data import image_sources
from benchctl.training.schedule import Schedule

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
"""The paper's claims as (method, reference, with the iris, claim): each is read as the method minus the reference
with the same seed, next to the paper's difference (on the paper's bench, which has no iris at 1088 rows)."""

NOT_TESTABLE = {
    ("holonet-lowdef2", True): "the bench's iris passes 0.5 x the full grid's Nyquist frequency, the half-definition "
                               "grid's own: nothing that reaches the image is lost by propagating at half definition",
}
"""Claims this bench cannot test, with the reason (their numbers are still shown)."""

MAX_HALF_WIDTH_DB = 1.0
VERDICT_RULE = (
    "A claim is read from differences paired by seed (method minus reference, same seed) and their 95 % "
    "t-interval. **Agrees** with the paper: the paper's difference lies inside the interval and the interval is at "
    f"most +-{MAX_HALF_WIDTH_DB:g} dB wide. **Disagrees**: the paper's difference lies outside the interval. "
    "**Not resolved**: fewer than two paired seeds, or an interval wider than that. **Not testable here**: the "
    "bench cannot show the effect (reason given). Every verdict is at the run's budget (see 'ended by').")


def _label(method: str, iris: bool) -> str:
    return method if iris else f"{method} (no iris)"


def _reading(curve: Sequence[dict[str, Any]], key: str, budget: float) -> dict[str, Any]:
    """The last evaluation at or before `budget` of `key` (the first one if none is)."""
    before = [e for e in curve if e[key] <= budget]
    return before[-1] if before else curve[0]


def _spread(values: Sequence[float]) -> tuple[float, float]:
    return statistics.mean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def collect(run_dir: Path) -> tuple[dict[str, Any], dict[tuple[str, bool], list[dict[str, Any]]], list[str]]:
    """The plan, the finished jobs grouped by (method, iris) in plan order, and the names of unfinished jobs (from
    the jobs' records, or from the report's CSVs where the job folders are gone)."""
    plan = read_plan(run_dir)
    groups: dict[tuple[str, bool], list[dict[str, Any]]] = {}
    unfinished = []
    from_csvs = not (Path(run_dir) / "jobs").is_dir() and (Path(run_dir) / "curves.csv").is_file()
    records = _from_csvs(run_dir, plan) if from_csvs else [read_done(run_dir, j["name"]) for j in plan["jobs"]]
    for job, done in zip(plan["jobs"], records):
        if done is None or not done["curve"]:
            unfinished.append(job["name"])
            continue
        groups.setdefault((job["method"], job["iris"]), []).append(done)
    return plan, groups, unfinished


def clock(groups: dict[tuple[str, bool], list[dict[str, Any]]]) -> str:
    """The clock of the equal-time reading: synchronised GPU seconds where every job ran on a GPU, else CPU."""
    everyone = [d for runs in groups.values() for d in runs]
    return "gpu_seconds" if everyone and all(d.get("gpu_seconds") for d in everyone) else "cpu_seconds"


def budgets(groups: dict[tuple[str, bool], list[dict[str, Any]]]) -> dict[str, tuple[int, float]]:
    """Per family, (equal steps, equal seconds of `clock`): the baseline's fewest steps and mean training time
    (over all finished jobs where the baseline has none)."""
    result = {}
    key = clock(groups)
    everyone = [d for runs in groups.values() for d in runs]
    for family, base in BASELINES.items():
        runs = groups.get((base, True)) or [d for d in everyone if VARIANTS[d["method"]].family == family]
        if runs:
            result[family] = (min(d["steps"] for d in runs), statistics.mean(d[key] for d in runs))
    return result


def reason_text(reason: str) -> str:
    """What ended a job, in the table's words ('converged' was the stopping rule's old name: a flat curve, which
    can also be a collapsed one)."""
    return "flat (stopping rule)" if reason in ("converged", "flat") else reason


def table_rows(groups: dict[tuple[str, bool], list[dict[str, Any]]], memory: dict[str, float]) -> list[dict[str, Any]]:
    """One row per (method, iris): seeds, what ended training, scores with their spread, ratios to the baseline."""
    equal = budgets(groups)
    key = clock(groups)
    rows: list[dict[str, Any]] = []
    for (method, iris), runs in groups.items():
        family = VARIANTS[method].family
        steps_budget, time_budget = equal[family]
        finals = [d["curve"][-1] for d in runs]
        at_steps = [_reading(d["curve"], "step", steps_budget) for d in runs]
        at_time = [_reading(d["curve"], key, time_budget) for d in runs]
        paper = PAPER.get(method)
        row: dict[str, Any] = {
            "method": _label(method, iris), "family": family, "iris": iris, "seeds": len(runs),
            "seed_list": " ".join(str(d["seed"]) for d in runs),
            "ended_by": ", ".join(sorted({reason_text(d["reason"]) for d in runs})),
            "steps": round(statistics.mean(d["steps"] for d in runs)),
            "cpu_minutes": round(statistics.mean(d[key] for d in runs) / 60, 2),
            "psnr_db": _spread([e["psnr"] for e in finals]), "ssim": statistics.mean(e["ssim"] for e in finals),
            "best_val_psnr_db": _spread([_best(d) for d in runs]),
            "equal_steps": steps_budget, "steps_psnr_db": _spread([e["psnr"] for e in at_steps]),
            "equal_cpu_seconds": round(time_budget, 1), "time_psnr_db": _spread([e["psnr"] for e in at_time]),
            "time_ended_before": sum(d[key] < time_budget for d in runs), "clock": key,
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


# Student's t at 0.975 (the two-sided 95 % interval) for 1 .. 30 degrees of freedom, from the standard tables.
_T975 = (12.706205, 4.302653, 3.182446, 2.776445, 2.570582, 2.446912, 2.364624, 2.306004, 2.262157, 2.228139,
         2.200985, 2.178813, 2.160369, 2.144787, 2.131450, 2.119905, 2.109816, 2.100922, 2.093024, 2.085963,
         2.079614, 2.073873, 2.068658, 2.063899, 2.059539, 2.055529, 2.051831, 2.048407, 2.045230, 2.042272)


def t975(dof: int) -> float:
    """Student's t quantile at 0.975 for `dof` degrees of freedom: the table to 30, then the Cornish-Fisher
    expansion about the normal quantile (within 2e-6 of the exact value beyond 30)."""
    if dof <= len(_T975):
        return _T975[dof - 1]
    z = statistics.NormalDist().inv_cdf(0.975)
    return (z + (z**3 + z) / (4 * dof) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * dof**2)
            + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * dof**3))


def t_interval(values: Sequence[float]) -> tuple[float, float, float] | None:
    """(mean, low, high): the 95 % t-interval of the mean of `values`; None below two values."""
    if len(values) < 2:
        return None
    mean = statistics.mean(values)
    half = t975(len(values) - 1) * statistics.stdev(values) / len(values) ** 0.5
    return mean, mean - half, mean + half


def verdict(interval: tuple[float, float, float] | None, paper_db: float, untestable: str | None = None) -> str:
    """The verdict VERDICT_RULE gives a claim."""
    if untestable:
        return "not testable here"
    if interval is None:
        return "not resolved"
    _, low, high = interval
    if not low <= paper_db <= high:
        return "disagrees"
    return "agrees" if (high - low) / 2 <= MAX_HALF_WIDTH_DB else "not resolved"


def comparisons(groups: dict[tuple[str, bool], list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Each of the paper's claims that this run can read: differences paired by seed where training ended and
    where validation was best, the 95 % t-interval of the first, the paper's difference and the verdict."""
    result = []
    for method, reference, iris, claim in COMPARISONS:
        mine, theirs = groups.get((method, iris)), groups.get((reference, iris))
        if not mine or not theirs:
            continue
        by_seed = {d["seed"]: d for d in theirs}
        pairs = [(d, by_seed[d["seed"]]) for d in mine if d["seed"] in by_seed]
        if not pairs:
            continue
        ends = [_end(a) - _end(b) for a, b in pairs]
        bests = [_best(a) - _best(b) for a, b in pairs]
        interval = t_interval(ends)
        paper = PAPER[method][0] - PAPER[reference][0]
        result.append({"claim": claim, "method": _label(method, iris), "reference": _label(reference, iris),
                       "pairs": len(pairs), "seeds": " ".join(str(a["seed"]) for a, _ in pairs),
                       "here_db": statistics.mean(ends), "ci_low_db": interval[1] if interval else None,
                       "ci_high_db": interval[2] if interval else None,
                       "per_seed_db": " ".join(f"{d:+.2f}" for d in ends),
                       "best_val_db": statistics.mean(bests), "paper_db": paper,
                       "verdict": verdict(interval, paper, NOT_TESTABLE.get((method, iris))),
                       "not_testable": NOT_TESTABLE.get((method, iris), "")})
    return result


def _pm(value: tuple[float, float], seeds: int) -> str:
    return f"{value[0]:.2f} +- {value[1]:.2f}" if seeds > 1 else f"{value[0]:.2f}"


def format_table(rows: Sequence[dict[str, Any]], dpac: tuple[float, float] | None) -> list[str]:
    """The Markdown table: where training ended, at equal steps and equal time, the paper, memory and speed."""
    def num(row: dict[str, Any], key: str, fmt: str) -> str:
        value = row.get(key)
        return "-" if value is None else format(value, fmt)

    minutes = "GPU-min" if rows and rows[0].get("clock") == "gpu_seconds" else "CPU-min"
    lines = [f"| method | seeds | ended by | steps | {minutes} | PSNR (dB), end | SSIM | vs base | "
             "at best validation | vs base | PSNR at equal steps "
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
            f"{_pm(r['time_psnr_db'], r['seeds'])} ({r['equal_cpu_seconds'] / 60:.1f} min"
            + (f"; {r['time_ended_before']} ended before: last score" if r.get("time_ended_before") else "")
            + ") | "
            f"{num(r, 'time_delta_db', '+.2f')} | {paper} | {num(r, 'paper_delta_db', '+.2f')} | "
            f"{num(r, 'train_step_peak_mib', '.0f')} | {num(r, 'memory_ratio', '.2f')} | "
            f"{r['inference_seconds']:.4f} | {num(r, 'speedup', '.2f')} |")
    if dpac is not None:
        lines.append(f"| dpac (classical reference) | - | - | - | - | {dpac[0]:.2f} | {dpac[1]:.3f} | - | - | - | - | "
                     "- | - | - | - | - | - | - | - | - |")
    return lines


def format_comparisons(found: Sequence[dict[str, Any]]) -> list[str]:
    """The claims' table: paired differences, their 95 % interval, the paper's, the verdict (VERDICT_RULE)."""
    lines = ["| the paper's claim | method - reference (same seed) | seeds | here (dB), end | 95 % interval (dB) | "
             "per seed (dB) | here (dB), at best validation | paper (dB) | verdict |",
             "| --- | --- | --- | ---: | ---: | --- | ---: | ---: | --- |"]
    for c in found:
        interval = f"{c['ci_low_db']:+.2f} .. {c['ci_high_db']:+.2f}" if c["ci_low_db"] is not None else "-"
        lines.append(f"| {c['claim']} | {c['method']} - {c['reference']} | {c['seeds']} | {c['here_db']:+.2f} | "
                     f"{interval} | {c['per_seed_db']} | {c['best_val_db']:+.2f} | {c['paper_db']:+.2f} | "
                     f"{c['verdict']} |")
    return lines


def per_image(groups: dict[tuple[str, bool], list[dict[str, Any]]],
              dpac: dict[str, Any]) -> tuple[list[str], list[dict[str, Any]]]:
    """Per held-out image and method: PSNR / SSIM where training ended, mean over the seeds that recorded them
    (Markdown lines and CSV rows; none for runs from before per-image scores were recorded)."""
    rows: list[dict[str, Any]] = []
    for (method, iris), runs in groups.items():
        recorded = [d["per_image"] for d in runs if d.get("per_image")]
        for i, first in enumerate(recorded[0] if recorded else []):
            rows.append({"image": first["image"], "method": _label(method, iris), "seeds": len(recorded),
                         "psnr_db": statistics.mean(r[i]["psnr"] for r in recorded),
                         "ssim": statistics.mean(r[i]["ssim"] for r in recorded)})
    rows += [{"image": e["image"], "method": "dpac", "seeds": 0, "psnr_db": e["psnr"], "ssim": e["ssim"]}
             for e in dpac.get("per_image", [])] if rows else []
    if not rows:
        return [], []
    methods = list(dict.fromkeys(r["method"] for r in rows))
    images = list(dict.fromkeys(r["image"] for r in rows))
    cell = {(r["image"], r["method"]): r for r in rows}
    lines = ["| image | " + " | ".join(methods) + " |", "| --- |" + " ---: |" * len(methods)]
    for image in images:
        lines.append(f"| {image} | " + " | ".join(
            f"{cell[image, m]['psnr_db']:.2f} / {cell[image, m]['ssim']:.3f}" if (image, m) in cell else "-"
            for m in methods) + " |")
    return lines, rows


def dpac_reference(run_dir: Path, plan: dict[str, Any]) -> dict[str, Any]:
    """DPAC's amplitude PSNR / SSIM on the run's held-out images and bench, per image and their mean (kept in
    dpac.json). A plan whose profile file has moved (a run reported from its CSVs elsewhere) names it by its
    file name."""
    path = Path(run_dir) / "dpac.json"
    if path.is_file():
        saved = json.loads(path.read_text())
        if "per_image" in saved:
            return dict(saved)
    profile = plan["profile"] if Path(plan["profile"]).is_file() else Path(plan["profile"]).stem
    bench = bench_for(plan | {"profile": profile}, {"iris": True})
    grid, roi = bench.section("slm").shape, bench.section("optics").roi
    each: list[dict[str, Any]] = []
    for source in image_sources(plan.get("held_out", DEFAULT_HELD_OUT)):
        scene = compute_scene(prepare_target(source.load(roi), grid, roi), Calibrated(bench), "dpac",
                              colours=[plan["colour"]])
        scores = next(c.scores for c in scene.colours if not c.skipped)
        each.append({"image": source.name, "psnr": scores["psnr_amplitude_db"], "ssim": scores["ssim_amplitude"]})
    result = {"psnr_db": statistics.mean(e["psnr"] for e in each), "ssim": statistics.mean(e["ssim"] for e in each),
              "per_image": each}
    write_json(path, result)
    return result


def _from_csvs(run_dir: Path, plan: dict[str, Any]) -> list[dict[str, Any] | None]:
    """The jobs' records rebuilt from a report's CSVs, for a run whose job folders are gone: each job's curve from
    curves.csv, its ending from its last step and the method's 'ended_by', inference time from reproduction.csv
    (per method), its per-image scores from per_image_seeds.csv where the run has one. None for a job the CSVs do not
    hold as finished."""
    curves: dict[str, list[dict[str, Any]]] = {}
    finished: set[str] = set()
    for row in _csv_rows(Path(run_dir) / "curves.csv"):
        curves.setdefault(row["job"], []).append(
            {"step": int(row["step"]), "cpu_seconds": float(row["cpu_seconds"]),
             "wall_seconds": float(row["wall_seconds"]), "val_psnr": float(row["val_psnr"]),
             "psnr": float(row["psnr"]), "ssim": float(row["ssim"])})
        if row["finished"] == "True":
            finished.add(row["job"])
    methods = {row["method"]: row for row in _csv_rows(Path(run_dir) / "reproduction.csv")}
    scored: dict[str, list[dict[str, Any]]] = {}
    if (Path(run_dir) / "per_image_seeds.csv").is_file():
        for row in _csv_rows(Path(run_dir) / "per_image_seeds.csv"):
            scored.setdefault(row["job"], []).append(
                {"image": row["image"], "psnr": float(row["psnr_db"]), "ssim": float(row["ssim"])})
    records: list[dict[str, Any] | None] = []
    for job in plan["jobs"]:
        curve = curves.get(job["name"], [])
        if job["name"] not in finished or not curve:
            records.append(None)
            continue
        row = methods[_label(job["method"], job["iris"])]
        steps = curve[-1]["step"]
        endings = [e.strip() for e in row["ended_by"].split(",")]
        reason = "step cap" if steps >= plan["max_steps"] else next(e for e in endings if e != "step cap")
        records.append({"name": job["name"], "method": job["method"], "seed": job["seed"], "iris": job["iris"],
                        "reason": reason, "steps": steps, "cpu_seconds": curve[-1]["cpu_seconds"],
                        "wall_seconds": curve[-1]["wall_seconds"], "curve": curve,
                        "inference_seconds": float(row["inference_seconds"])}
                       | ({"per_image": scored[job["name"]]} if job["name"] in scored else {}))
    return records


def write_report(run_dir: Path, out: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """reproduction.md / .csv, comparisons.csv, per_image.csv (mean over seeds), per_image_seeds.csv (each job's),
    curves.csv and the plots from the finished jobs; the rows. A run reported from its CSVs keeps its
    reproduction.csv, curves.csv and per_image_seeds.csv (they are its data)."""
    run_dir = Path(run_dir)
    plan, groups, unfinished = collect(run_dir)
    from_csvs = not (run_dir / "jobs").is_dir()
    memory_path = run_dir / "memory.json"
    memory = json.loads(memory_path.read_text()) if memory_path.is_file() else {}
    if from_csvs and not memory and (run_dir / "reproduction.csv").is_file():
        memory = {r["method"]: float(r["train_step_peak_mib"]) for r in _csv_rows(run_dir / "reproduction.csv")
                  if r["train_step_peak_mib"] and r["iris"] == "True"}
    dpac = dpac_reference(run_dir, plan)
    rows = table_rows(groups, memory) if groups else []
    found = comparisons(groups)
    lines = format_table(rows, (dpac["psnr_db"], dpac["ssim"]))
    image_lines, image_rows = per_image(groups, dpac)
    size = plan["size"]
    schedule = Schedule(plan["lr"], plan.get("warmup", 0), plan.get("decay", "none"), plan["max_steps"])
    header = [f"Command: `{plan['command']}`" if plan.get("command") else "",
              f"Bench: {size[0]}x{size[1]} (Fresnel-scaled), {plan['colour']}; data {plan['data']}; validation "
              f"(stopping rule): procedural images {VALIDATION_FIRST}-{VALIDATION_FIRST + VALIDATION_COUNT - 1}; "
              f"scores: held-out images {plan.get('held_out', DEFAULT_HELD_OUT)}, mean over them; Adam, "
              f"{schedule.describe()}; stop: < {plan['min_gain_db']:g} dB per doubling of steps at "
              f"{plan.get('patience', 1)} power-of-two step(s) in a row from step {plan['min_steps']} on, cap "
              f"{plan['max_steps']} steps; {plan['threads']} torch thread(s) per job; device "
              f"{plan.get('device', 'cpu')}.",
              f"Change of plan: {plan['rule_change']}." if plan.get("rule_change") else "",
              f"Unfinished jobs (not in the table): {', '.join(unfinished)}." if unfinished else "", ""]
    claims = ["", "Verdicts: " + VERDICT_RULE, "", *format_comparisons(found)]
    images = ["", "Per held-out image, where training ended (PSNR dB / SSIM, mean over the seeds):", "",
              *image_lines] if image_lines else \
        ["", "No per-image scores: " + ("this run was reported from its CSVs; its checkpoints are gone."
                                        if from_csvs else "its jobs predate per-image records.")]
    for line in lines + claims + images:
        out(line)
    written = [write_csv(run_dir / "comparisons.csv", found)]
    if image_rows:
        written.append(write_csv(run_dir / "per_image.csv", image_rows))
    if not from_csvs:
        rows_csv = [{k: (f"{v[0]:.3f}" if isinstance(v, tuple) else v) for k, v in r.items()}
                    | {f"{k}_sd": f"{v[1]:.3f}" for k, v in r.items() if isinstance(v, tuple)} for r in rows]
        written += [write_csv(run_dir / "reproduction.csv", rows_csv),
                    write_csv(run_dir / "curves.csv", _curves(plan, run_dir))]
        seeds_rows = _image_scores(groups)
        if seeds_rows:
            written.append(write_csv(run_dir / "per_image_seeds.csv", seeds_rows))
    text = "\n".join(header + lines + claims + images) + "\n"
    written.append(atomic_write_bytes(run_dir / "reproduction.md", text.encode()))
    key = clock(groups)
    for x, label, name in (("step", "training step", "psnr_vs_step.png"),
                           (key, f"training {'GPU' if key == 'gpu_seconds' else 'CPU'} seconds",
                            "psnr_vs_seconds.png")):
        plot = _plot(groups, x, label, run_dir / name, dpac["psnr_db"])
        if plot is not None:
            written.append(plot)
    out("wrote " + ", ".join(str(p) for p in written))
    return rows


def _csv_rows(path: Path) -> list[dict[str, str]]:
    import csv

    with path.open() as handle:
        return list(csv.DictReader(handle))


def _curves(plan: dict[str, Any], run_dir: Path) -> list[dict[str, Any]]:
    rows = []
    for job in plan["jobs"]:
        done = read_done(run_dir, job["name"])
        for e in done["curve"] if done else read_progress(run_dir, job["name"]):
            rows.append({"job": job["name"], "method": job["method"], "seed": job["seed"], "iris": job["iris"],
                         "finished": done is not None} | e)
    return rows


def _image_scores(groups: dict[tuple[str, bool], list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Each finished job's held-out scores per image, where training ended (one row per job and image)."""
    return [{"job": d["name"], "method": d["method"], "seed": d["seed"], "iris": d["iris"], "image": e["image"],
             "psnr_db": e["psnr"], "ssim": e["ssim"]}
            for runs in groups.values() for d in runs for e in d.get("per_image") or []]


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
    ax.set_ylabel("PSNR, amplitude, mean over the held-out images (dB)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    return atomic_write_bytes(path, buffer.getvalue())
