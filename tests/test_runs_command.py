"""`benchctl runs`: run folders listed with how they ended and their headline, scores side by side, old runs
removed only when confirmed, never one that may still be running unless forced; listing changes nothing."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import one_error_line

from benchctl.cli import main
from benchctl.runner.engine import run_procedure
from benchctl.runner.record import create_run

SCORED = """\
from benchctl.files import write_json
from benchctl.runner.procedure import Parameters, Step

DESCRIPTION = "writes a score"
PARAMETERS = Parameters


def report(context):
    write_json(context.path("metrics.json"), {{"procedure": "scored", "targets": [
        {{"label": "bars", "merged": {{"capture": {{"psnr_srgb_db": {psnr}, "ssim_srgb": 0.5}}}},
          "colours": {{"red": {{"gain": 2.0, "capture": {{"psnr_amplitude_db": {red}}}}}}}}}]}})
    return {{"headline": ["bars: merged capture PSNR {psnr} dB sRGB", "second line"]}}


def plan(context):
    return [Step("report", "report", report)]
"""


def scored_run(tmp_path: Path, profile: Path, name: str, psnr: float, red: float | None) -> Path:
    procedure = tmp_path / f"{name}.py"
    procedure.write_text(SCORED.format(psnr=psnr, red=red if red is not None else '"n/a"'))
    outcome = run_procedure(procedure, profile=str(profile), out=tmp_path / "runs", say=lambda _: None)
    assert outcome.folder is not None
    return outcome.folder


@pytest.fixture
def three_runs(tmp_path: Path, small_profile_path: Path) -> tuple[Path, Path, Path]:
    first = scored_run(tmp_path, small_profile_path, "first", 18.1, 20.25)
    second = scored_run(tmp_path, small_profile_path, "second", 17.95, None)
    crashed = create_run(tmp_path / "runs", "crashed", {"procedure": "colour-capture", "profile": "small"}, {})
    (tmp_path / "runs" / "notes").mkdir()  # not a run: left alone
    return first, second, crashed.folder


def test_runs_lists_each_run_with_how_it_ended_and_its_headline(tmp_path: Path, three_runs: tuple[Path, Path, Path],
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    first, second, unfinished = three_runs
    before = {path: path.read_bytes() for path in (tmp_path / "runs").rglob("*") if path.is_file()}
    assert main(["runs", "--out", str(tmp_path / "runs")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith(f"{first.name}  first.py on small  finished  ")
    assert lines[0].endswith("  bars: merged capture PSNR 18.1 dB sRGB (+1 more)")
    assert lines[1].startswith(f"{second.name}  second.py on small  finished  ")
    assert lines[2].startswith(f"{unfinished.name}  colour-capture on small  no stop record  ")
    assert lines[3].startswith(f"3 run(s) in {tmp_path / 'runs'}, ")
    assert {path: path.read_bytes() for path in (tmp_path / "runs").rglob("*") if path.is_file()} == before


def test_runs_compare_puts_scores_side_by_side(tmp_path: Path, three_runs: tuple[Path, Path, Path],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    first, second, _ = three_runs
    assert main(["runs", "compare", first.name, str(second), "--out", str(tmp_path / "runs")]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    assert rows == [["score", first.name, second.name], ["procedure", "first.py", "second.py"],
                    ["targets[bars].merged.capture.psnr_srgb_db", "18.1", "17.95"],
                    ["targets[bars].merged.capture.ssim_srgb", "0.5", "0.5"],
                    ["targets[bars].colours.red.capture.psnr_amplitude_db", "20.25", "-"]]


def test_runs_remove_lists_first_and_never_a_run_that_may_still_run(
        tmp_path: Path, three_runs: tuple[Path, Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    first, second, unfinished = three_runs
    out = ["--out", str(tmp_path / "runs")]
    assert main(["runs", "remove", first.name, *out]) == 0
    assert capsys.readouterr().out.splitlines()[-1].endswith("add --yes to remove them") and first.is_dir()
    line = one_error_line(capsys, ["runs", "remove", "--older-than", "0", "--yes", *out])
    assert line == (f"benchctl: error: {unfinished}: the run has no stop record: it may still be running (or ended "
                    "by kill -9 or a power loss); add --force to remove it anyway")
    assert first.is_dir() and second.is_dir() and unfinished.is_dir()
    assert main(["runs", "remove", first.name, str(second), "--yes", *out]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("2 run(s) removed, ")
    assert not first.exists() and not second.exists()
    assert main(["runs", "remove", "--older-than", "0", "--yes", "--force", *out]) == 0
    assert not unfinished.exists() and (tmp_path / "runs" / "notes").is_dir()
    assert main(["runs", *out]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == f"no runs in {tmp_path / 'runs'}"


def test_runs_refuses_what_is_no_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "notes").mkdir()
    assert one_error_line(capsys, ["runs", "compare", str(tmp_path / "notes")]) == (
        f"benchctl: error: {tmp_path / 'notes'}: not a benchctl run folder (no run.json)")
    assert one_error_line(capsys, ["runs", "remove", "--out", str(tmp_path)]) == (
        "benchctl: error: name the runs to remove, or give --older-than DAYS (not both)")
    run = create_run(tmp_path / "runs", "damaged", {"procedure": "x"}, {}).folder
    (run / "metrics.json").write_text("{oops")
    line = one_error_line(capsys, ["runs", "compare", str(run)])
    assert line.startswith(f"benchctl: error: {run / 'metrics.json'}: cannot read metrics: ")
    (run / "run.json").write_text(json.dumps([1]))
    assert main(["runs", "--out", str(tmp_path / "runs")]) == 0  # listed as damaged; the others stay listed
    listed = capsys.readouterr().out.splitlines()[0]
    assert listed.startswith(f"{run.name}  ? on ?  damaged record ({run / 'run.json'}: (top level): expected a JSON "
                             "object {...}, got list)")
    line = one_error_line(capsys, ["runs", "remove", str(run), "--yes", "--out", str(tmp_path / "runs")])
    assert line.startswith(f"benchctl: error: {run}: damaged record (") and line.endswith("add --force to remove it "
                                                                                          "anyway")
    assert main(["runs", "remove", str(run), "--yes", "--force", "--out", str(tmp_path / "runs")]) == 0
    assert not run.exists()


def test_runs_remove_removes_only_run_folders_below_the_runs_root(
        tmp_path: Path, three_runs: tuple[Path, Path, Path], capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """`runs remove . --yes` in a folder holding a run.json emptied it and then crashed; now only a folder directly
    below the runs root, named as runs are and holding a run.json, is removed."""
    first, _, _ = three_runs
    runs = tmp_path / "runs"
    work = tmp_path / "work"
    work.mkdir()
    (work / "run.json").write_text("{}")
    (work / "thesis.tex").write_text("kept")
    elsewhere = tmp_path / "elsewhere" / first.name  # named like a run, not below the root
    elsewhere.mkdir(parents=True)
    (elsewhere / "run.json").write_text("{}")
    (runs / "link").symlink_to(first, target_is_directory=True)
    (runs / "20260101-000000-empty").mkdir()  # named like a run, no run.json
    monkeypatch.chdir(work)
    for name in (".", str(runs / "link"), str(elsewhere), str(runs / ".."), str(runs)):
        line = one_error_line(capsys, ["runs", "remove", name, "--yes", "--force", "--out", str(runs)])
        assert line == (f"benchctl: error: {name}: not a run folder below {runs} (one is named "
                        f"{runs}/<YYYYmmdd-HHMMSS>-<name>; --out names the runs root): nothing removed"), name
    line = one_error_line(capsys, ["runs", "remove", "20260101-000000-empty", "--yes", "--out", str(runs)])
    assert line == (f"benchctl: error: {runs / '20260101-000000-empty'}: not a benchctl run folder (no run.json): "
                    "nothing removed")
    monkeypatch.chdir(first)
    for name in (".", str(first)):
        line = one_error_line(capsys, ["runs", "remove", name, "--yes", "--out", str(runs)])
        assert line == (f"benchctl: error: {name}: holds the current folder; change to another one first: nothing "
                        "removed")
    assert (work / "thesis.tex").read_text() == "kept" and (elsewhere / "run.json").is_file() and first.is_dir()
