"""`benchctl runs`: the run folders under runs/ at a glance, their scores side by side, and removing old ones.

Read-only on what the run record writes (runner.record: run.json with its start and stop records, steps.jsonl whose
last report step carries the headline; metrics.json from the procedure's report): listing or comparing a run
changes nothing in it. Removing one needs the stop record unless forced (a run without one may still be running),
and is only listed until confirmed with `yes`; only what is recognisably a run folder is removed: a folder directly
below the runs root, named as `create_run` names one, holding a run.json.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchctl.errors import BenchctlError
from benchctl.memory import size_text
from benchctl.runner.record import RUN_FILE, RUN_FOLDER, RunRecord, run_folder_lock

METRICS_FILE = "metrics.json"  # written by each procedure's report (runner.report)
SWEEP_FILE = "sweep.json"  # written by `bench sweep` (benchmarks.sweep): its trials, values, seeds and scores
SCORE_WORDS = ("psnr", "ssim", "residual", "rms")  # the figures `compare` puts side by side
UNFINISHED = "no stop record"
DAMAGED = "damaged record"


@dataclass(frozen=True)
class Run:
    """One run folder as its records describe it."""

    folder: Path
    procedure: str
    profile: str
    start: str
    # finished (", calibration not stored" when one failed its acceptance test), failed, interrupted, UNFINISHED
    # (running, or ended by kill -9 / power loss) or DAMAGED (its run.json or step log cannot be read)
    status: str
    headline: list[str]
    bytes: int

    @property
    def started_unix(self) -> float:
        try:
            return time.mktime(time.strptime(self.start[:19], "%Y-%m-%dT%H:%M:%S"))
        except ValueError:
            return os.stat(self.folder / RUN_FILE).st_mtime


def read_run(folder: Path) -> Run:
    """The run in `folder`; a BenchctlError if it is not a run folder or its record cannot be read."""
    folder = Path(folder)
    if not (folder / RUN_FILE).is_file():
        raise BenchctlError(f"{folder}: not a benchctl run folder (no {RUN_FILE})")
    record = RunRecord(folder)
    try:
        info = record.info()
        events = record.events()
    except BenchctlError as exc:  # listed as damaged: the other runs stay readable, and it can be removed (forced)
        return Run(folder, "?", "?", "?", f"{DAMAGED} ({exc})", [], _size(folder))
    headline = next((list(map(str, e["result"]["headline"])) for e in reversed(events) if e["event"] == "done"
                     and isinstance(e["result"].get("headline"), list) and e["result"]["headline"]), [])
    stop = info["stop"] if isinstance(info.get("stop"), dict) else {}
    status = str(stop.get("status", UNFINISHED)) + (", calibration not stored" if stop.get("not_stored") else "")
    return Run(folder, str(info.get("procedure", "?")), str(info.get("profile", "?")), str(info.get("start", "?")),
               status, headline, _size(folder))


def _size(folder: Path) -> int:
    return sum(entry.stat().st_size for entry in folder.rglob("*") if entry.is_file() and not entry.is_symlink())


def find_runs(root: Path) -> list[Run]:
    """Every run folder directly under `root`, oldest first (folders that are not runs are left out)."""
    root = Path(root)
    if not root.is_dir():
        return []
    return sorted((read_run(child) for child in root.iterdir() if (child / RUN_FILE).is_file()),
                  key=lambda run: run.start)


def list_lines(root: Path) -> list[str]:
    """One line per run: folder, procedure, profile, status, size, and its headline's first line."""
    runs = find_runs(root)
    if not runs:
        return [f"no runs in {root}"]
    lines = []
    for run in runs:
        headline = run.headline[:1] + ([f"(+{len(run.headline) - 1} more)"] if len(run.headline) > 1 else [])
        lines.append("  ".join([run.folder.name, f"{run.procedure} on {run.profile}", run.status, size_text(run.bytes),
                                *headline]).replace("  (+", " (+"))
    total = sum(run.bytes for run in runs)
    return lines + [f"{len(runs)} run(s) in {root}, {size_text(total)}"]


def _flat(value: Any, key: str = "") -> Iterable[tuple[str, float]]:
    """The numbers in a metrics tree as (dotted key, value); a list of records is keyed by each one's label."""
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        yield key, float(value)
    elif isinstance(value, dict):
        for name, item in value.items():
            yield from _flat(item, f"{key}.{name}" if key else str(name))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            label = next((item[k] for k in ("label", "colour", "name", "iteration") if isinstance(item, dict)
                          and k in item), index)
            yield from _flat(item, f"{key}[{label}]")


def scores(folder: Path) -> dict[str, float]:
    """The scores in a run's metrics.json (keys naming PSNR, SSIM, a residual or an RMS error)."""
    path = Path(folder) / METRICS_FILE
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        raise BenchctlError(f"{path}: cannot read metrics: {exc}") from None
    return {key: value for key, value in _flat(data)
            if any(word in key.rsplit(".", 1)[-1].lower() for word in SCORE_WORDS)}


def sweep_trials(folder: Path) -> list[tuple[str, str, dict[str, float]]]:
    """A sweep's trials (`bench sweep`'s sweep.json) as (name, state, values and scores); [] for other folders."""
    path = Path(folder) / SWEEP_FILE
    if not path.is_file():
        return []
    try:
        trials = json.loads(path.read_text())["trials"]
        columns = []
        for trial in trials:
            values = {k: float(v) for k, v in trial["params"].items() if not isinstance(v, str)}
            seed = math.nan if trial["seed"] is None else float(trial["seed"])
            columns.append((trial["name"], f"sweep: {trial['state'].lower()}",
                            values | {"seed": seed} | dict(trial["scores"])))
        return columns
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BenchctlError(f"{path}: cannot read the sweep's trials: {exc}") from None


def compare_lines(folders: list[Path]) -> list[str]:
    """The runs' scores side by side: one row per score any of them has, one column per run ('-': not there); a
    sweep's folder gives one column per trial, with its values and seed."""
    columns: list[tuple[str, str, dict[str, float]]] = []
    for folder in folders:
        trials = sweep_trials(folder)
        if trials:
            columns += trials
        else:
            run = read_run(folder)
            columns.append((run.folder.name, run.procedure, scores(run.folder)))
    table = [found for _, _, found in columns]
    keys = list(dict.fromkeys(key for found in table for key in found))
    if not keys:
        return ["no scores in " + ", ".join(f"{Path(folder) / METRICS_FILE}" for folder in folders)]
    names = [name for name, _, _ in columns]
    width = max(len("score"), *(len(key) for key in keys))
    widths = [max(len(name), 9) for name in names]
    lines = ["score".ljust(width) + "".join(f"  {name:>{size}}" for name, size in zip(names, widths)),
             "procedure".ljust(width) + "".join(f"  {what:>{size}}" for (_, what, _), size in zip(columns, widths))]
    for key in keys:
        cells = [f"{found[key]:.4g}" if key in found else "-" for found in table]
        lines.append(key.ljust(width) + "".join(f"  {cell:>{size}}" for cell, size in zip(cells, widths)))
    return lines


def _removable(folder: Path, root: Path) -> Path:
    """`folder` if it is recognisably a run folder below `root`: directly in it (not a link), named as runs are, with
    a run.json, and not holding the current folder; else a BenchctlError saying which of these it is not."""
    real = folder.resolve()
    if folder.is_symlink() or real.parent != root.resolve() or not RUN_FOLDER.fullmatch(real.name):
        raise BenchctlError(f"{folder}: not a run folder below {root} (one is named {root}/<YYYYmmdd-HHMMSS>-<name>; "
                            "--out names the runs root): nothing removed")
    if not (real / RUN_FILE).is_file():
        raise BenchctlError(f"{folder}: not a benchctl run folder (no {RUN_FILE}): nothing removed")
    if real == Path.cwd().resolve() or real in Path.cwd().resolve().parents:
        raise BenchctlError(f"{folder}: holds the current folder; change to another one first: nothing removed")
    return folder


def remove_runs(folders: list[Path], root: Path, yes: bool, force: bool) -> list[str]:
    """Remove run folders below `root` (only listed without `yes`): only what is recognisably a run folder; one
    without a stop record or with a damaged record only with `force`, and never one a process is writing (its
    folder's lock held)."""
    runs = [read_run(_removable(folder, root)) for folder in folders]
    for run in runs:
        with run_folder_lock(run.folder):  # refused, naming the holder, while a run writes it
            pass
    for run in runs:
        if not force and run.status == UNFINISHED:
            raise BenchctlError(f"{run.folder}: the run has {UNFINISHED}: it may still be running (or ended by kill -9 "
                                "or a power loss); add --force to remove it anyway")
        if not force and run.status.startswith(DAMAGED):
            raise BenchctlError(f"{run.folder}: {run.status}; add --force to remove it anyway")
    total = sum(run.bytes for run in runs)
    if not yes:
        return [f"would remove {run.folder} ({run.status}, {size_text(run.bytes)})" for run in runs] + [
            f"{len(runs)} run(s), {size_text(total)}: add --yes to remove them"]
    removed: list[str] = []
    for run in runs:
        try:
            shutil.rmtree(run.folder)
        except OSError as exc:
            raise BenchctlError(f"{run.folder}: cannot remove it all: {exc.strerror or exc} (removed before it: "
                                f"{', '.join(removed) or 'none'})") from None
        removed.append(str(run.folder))
    return [f"removed {run.folder} ({size_text(run.bytes)})" for run in runs] + [
        f"{len(runs)} run(s) removed, {size_text(total)} freed"]


def older_than(root: Path, days: float) -> list[Path]:
    """The run folders under `root` that started more than `days` days ago."""
    limit = time.time() - days * 86400
    return [run.folder for run in find_runs(root) if run.started_unix < limit]
