"""`bench sweep`: Optuna trials of one learned method, each a one-job `bench reproduce` run with its own seed, the
study in a journal file in the run folder, resumable; `runs compare` reads the trials."""

from __future__ import annotations

import json
from pathlib import Path

import optuna
import pytest
from optuna.storages import JournalStorage
from optuna.storages.journal import JournalFileBackend

from benchctl.benchmarks import sweep
from benchctl.cli import main
from benchctl.runner.runs import compare_lines


@pytest.mark.slow  # three trials' subprocesses, each importing torch
def test_a_sweep_records_each_trial_with_its_seed_and_continues_an_interrupted_trial(
        capsys, tmp_path: Path, small_profile_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "sweep"
    argv = ["bench", "sweep", "--profile", str(small_profile_path), "--method", "ccnn", "--trials", "2",
            "--size", "32x48", "--data", "procedural:2", "--max-steps", "8", "--min-steps", "4",
            "--warmup-choices", "0,2", "--seed", "7"]
    finish = sweep._finish
    calls = {"n": 0}

    def interrupted(*args: object) -> None:
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt  # the second trial is asked, its plan written, then the sweep stops
        finish(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(sweep, "_finish", interrupted)
    assert main([*argv, "--out", str(out)]) == 130
    storage = JournalStorage(JournalFileBackend(str(out / "sweep.journal")))
    states = [t.state for t in optuna.load_study(study_name="sweep", storage=storage).get_trials()]
    assert states == [optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.RUNNING]
    monkeypatch.setattr(sweep, "_finish", finish)
    capsys.readouterr()
    assert main(["bench", "sweep", "--resume", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("trial 1: continuing (lr ")  # the same trial, not a new one
    trials = json.loads((out / "sweep.json").read_text())["trials"]
    assert [(t["name"], t["state"], t["seed"], t["steps"]) for t in trials] == \
        [("trial-000", "COMPLETE", 7, 8), ("trial-001", "COMPLETE", 8, 8)]
    for trial, number in zip(trials, (0, 1)):
        plan = json.loads((out / "trials" / f"{number:03d}" / "plan.json").read_text())
        assert plan["seeds"] == [trial["seed"]] and plan["lr"] == trial["params"]["lr"]
        assert plan["warmup"] == trial["params"]["warmup"] in (0, 2) and plan["decay"] == trial["params"]["decay"]
        assert 1e-4 <= trial["params"]["lr"] <= 2e-3
    study = optuna.load_study(study_name="sweep", storage=storage)
    assert [t.value for t in study.get_trials()] == [t["scores"]["val_psnr_best_db"] for t in trials]
    lines = compare_lines([out])
    assert lines[0].split() == ["score", "trial-000", "trial-001"]
    row = next(line for line in lines if line.startswith("seed"))
    assert row.split()[1:] == ["7", "8"]
    assert any(line.startswith("val_psnr_best_db") for line in lines)
    assert main([*argv, "--out", str(out)]) == 2 and "--resume" in capsys.readouterr().err


def test_sweep_mistakes_are_one_line(capsys, tmp_path: Path, small_profile_path: Path) -> None:
    for extra, message in ((["--lr-range", "1e-3:1e-4"], "--lr-range 0.001:0.0001"),
                           (["--decay-choices", "linear"], "--decay-choices"),
                           (["--warmup-choices", "9000", "--max-steps", "100"], "--warmup 9000 must be shorter")):
        code = main(["bench", "sweep", "--profile", str(small_profile_path), "--method", "ccnn", "--size", "32x48",
                     "--out", str(tmp_path / "s"), *extra])
        err = capsys.readouterr().err
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "s" / "sweep-settings.json").exists()
