"""`benchctl bench sweep`: a hyperparameter search (learning rate, warm-up, decay) for one learned method, through
Optuna, its state in the run folder.

Each trial is a `bench reproduce` run of one job (`trials/<NNN>/`, the same recipe, stopping rule and exact
resume) with the values Optuna asks for and its own seed (the sweep's first seed + the trial's number, recorded);
its objective is the best validation PSNR the job reached (the held-out images are never chosen on). The study
lives in `sweep.journal`, Optuna's append-only file journal (no database server). Interrupted, `--resume DIR`
first finishes a trial that was running (its job continues from its saved state and the result is told to the
same trial), then asks for new ones until `--trials` have finished. `sweep.json` lists every trial with its
values, seed and scores, which `benchctl runs compare DIR` shows side by side.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from benchctl.benchmarks.reproduce import new_plan, run_reproduction
from benchctl.benchmarks.reproduce_job import read_done, read_plan
from benchctl.errors import BadValueError, BenchctlError
from benchctl.files import ensure_dir, write_json
from benchctl.profiles import Profile
from benchctl.training.schedule import DECAYS

SETTINGS_FILE = "sweep-settings.json"
TABLE_FILE = "sweep.json"  # the layout `runs compare` reads (runner.runs.SWEEP_FILE)
JOURNAL_FILE = "sweep.journal"
STUDY = "sweep"


def _optuna() -> Any:
    try:
        import optuna
    except ImportError:
        raise BenchctlError("bench sweep needs Optuna: pip install 'benchctl[sweeps]'") from None
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return optuna


def _study(run_dir: Path, seed: int) -> Any:
    optuna = _optuna()
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    storage = JournalStorage(JournalFileBackend(str(Path(run_dir) / JOURNAL_FILE)))
    return optuna.create_study(study_name=STUDY, storage=storage, direction="maximize", load_if_exists=True,
                               sampler=optuna.samplers.TPESampler(seed=seed))


def new_sweep(run_dir: Path, profile: Profile, *, method: str, trials: int, lr: tuple[float, float],
              warmup: Sequence[int], decay: Sequence[str], seed: int, recipe: dict[str, Any]) -> dict[str, Any]:
    """Write the sweep's settings into a new `run_dir` (refusing one that holds a sweep) and return them."""
    run_dir = Path(run_dir)
    if (run_dir / SETTINGS_FILE).exists():
        raise BenchctlError(f"{run_dir} already holds a sweep: continue it with --resume {run_dir}")
    if not 0 < lr[0] <= lr[1] <= 0.1:
        raise BadValueError(f"--lr-range {lr[0]:g}:{lr[1]:g}: expected LOW:HIGH with 0 < LOW <= HIGH <= 0.1")
    if not 1 <= trials <= 1000:
        raise BadValueError(f"--trials must lie between 1 and 1000, got {trials}")
    unknown = [d for d in decay if d not in DECAYS]
    if unknown or not decay:
        raise BadValueError(f"--decay-choices: expected some of {', '.join(DECAYS)}, got {','.join(decay) or 'none'}")
    if not warmup or any(w < 0 for w in warmup):
        raise BadValueError("--warmup-choices: expected warm-up step counts >= 0, e.g. 0,64,256")
    settings = {"profile": str(Path(profile.path).resolve()) if profile.path else None, "method": method,
                "trials": trials, "lr": list(lr), "warmup": list(warmup), "decay": list(decay), "seed": seed,
                "recipe": recipe}
    # one line for a recipe the trials would refuse: a plan checked (and removed) before anything is recorded
    probe = run_dir / "trials" / "check"
    new_plan(probe, profile, methods=[method], seeds=[seed], warmup=max(warmup), decay=decay[0], **recipe)
    (probe / "plan.json").unlink()
    probe.rmdir()
    write_json(ensure_dir(run_dir) / SETTINGS_FILE, settings)
    return settings


def run_sweep(run_dir: Path, profile: Profile, out: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """Run (or continue) the sweep in `run_dir` until its trials have finished; the trials' table."""
    run_dir = Path(run_dir)
    path = run_dir / SETTINGS_FILE
    if not path.is_file():
        raise BenchctlError(f"{run_dir}: not a sweep (no {SETTINGS_FILE}); start one with --out {run_dir}")
    settings = json.loads(path.read_text())
    optuna = _optuna()
    study = _study(run_dir, settings["seed"])
    running = [t for t in study.get_trials(deepcopy=False) if t.state == optuna.trial.TrialState.RUNNING]
    for trial in running:  # interrupted: its job continues exactly, its result goes to the same trial
        out(f"trial {trial.number}: continuing ({_values(trial.params)})")
        if not (_trial_dir(run_dir, trial.number) / "plan.json").is_file():  # stopped before its plan was written
            _plan_trial(run_dir, profile, settings, trial.number, trial.params, trial.user_attrs["seed"])
        _finish(run_dir, study, trial.number, out)
    while (done := _complete(study, optuna)) < settings["trials"]:
        trial = study.ask()
        params = {"lr": trial.suggest_float("lr", *settings["lr"], log=True),
                  "warmup": trial.suggest_categorical("warmup", settings["warmup"]),
                  "decay": trial.suggest_categorical("decay", settings["decay"])}
        seed = settings["seed"] + trial.number
        trial.set_user_attr("seed", seed)
        out(f"trial {trial.number} ({done + 1} of {settings['trials']}): {_values(params)}, seed {seed}")
        _plan_trial(run_dir, profile, settings, trial.number, params, seed)
        _finish(run_dir, study, trial.number, out)
    return write_table(run_dir, study, out)


def _plan_trial(run_dir: Path, profile: Profile, settings: dict[str, Any], number: int, params: dict[str, Any],
                seed: int) -> None:
    new_plan(_trial_dir(run_dir, number), profile, methods=[settings["method"]], seeds=[seed], lr=params["lr"],
             warmup=params["warmup"], decay=params["decay"], **settings["recipe"])


def _trial_dir(run_dir: Path, number: int) -> Path:
    return Path(run_dir) / "trials" / f"{number:03d}"


def _values(params: dict[str, Any]) -> str:
    return ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in params.items())


def _complete(study: Any, optuna: Any) -> int:
    return sum(t.state == optuna.trial.TrialState.COMPLETE for t in study.get_trials(deepcopy=False))


def _finish(run_dir: Path, study: Any, number: int, out: Callable[[str], None]) -> None:
    """Train trial `number`'s job to its end and tell the study its best validation PSNR (a job that diverged or
    stopped learning fails the trial)."""
    folder = _trial_dir(run_dir, number)
    run_reproduction(folder, jobs=1, memory=False, out=lambda line: None)
    job = read_plan(folder)["jobs"][0]["name"]
    done = read_done(folder, job)
    assert done is not None
    best = max((e["val_psnr"] for e in done["curve"]), default=math.nan)
    if done["reason"] in ("diverged", "stopped learning") or not math.isfinite(best):
        study.tell(number, state=_optuna().trial.TrialState.FAIL)
        out(f"trial {number}: {done['reason']} at step {done['steps']}: failed")
        return
    study.tell(number, best)
    out(f"trial {number}: best validation {best:.2f} dB ({done['reason']} at step {done['steps']}, held-out "
        f"{done['curve'][-1]['psnr']:.2f} dB at the end)")


def write_table(run_dir: Path, study: Any, out: Callable[[str], None] = print) -> list[dict[str, Any]]:
    """`sweep.json`: every trial with its values, seed, state and scores (best validation, held-out at the end)."""
    rows = []
    for trial in study.get_trials(deepcopy=False):
        folder = _trial_dir(run_dir, trial.number)
        plan = read_plan(folder) if (folder / "plan.json").is_file() else None
        done = read_done(folder, plan["jobs"][0]["name"]) if plan else None
        scores = {}
        if done and done["curve"]:
            scores = {"val_psnr_best_db": max(e["val_psnr"] for e in done["curve"]),
                      "psnr_amplitude_db": done["curve"][-1]["psnr"], "ssim_amplitude": done["curve"][-1]["ssim"]}
        rows.append({"name": f"trial-{trial.number:03d}", "state": trial.state.name,
                     "seed": trial.user_attrs.get("seed"), "params": trial.params,
                     "steps": done["steps"] if done else None, "scores": scores})
    write_json(Path(run_dir) / TABLE_FILE, {"kind": "sweep", "trials": rows})
    best = max((r for r in rows if r["scores"]), key=lambda r: r["scores"]["val_psnr_best_db"], default=None)
    if best:
        out(f"best: {best['name']} ({_values(best['params'])}, seed {best['seed']}): validation "
            f"{best['scores']['val_psnr_best_db']:.2f} dB; all trials in {Path(run_dir) / TABLE_FILE} "
            f"(benchctl runs compare {run_dir})")
    return rows
