"""`benchctl run --events FD`: the run's events as JSON lines for a program that follows it (the console), the same
events its step log records, framed by where the run is and how it stopped."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import one_error_line
from console_bench import POWER_SWEEP


def _run(tmp_path: Path, profile: Path, *options: str, pass_fds: tuple[int, ...] = ()) -> subprocess.Popen[str]:
    procedure = tmp_path / "sweep.toml"
    procedure.write_text(POWER_SWEEP)
    return subprocess.Popen([sys.executable, "-m", "benchctl", "run", str(procedure), "--profile", str(profile),
                             "--out", str(tmp_path / "runs"), *options], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, pass_fds=pass_fds)


@pytest.mark.slow
def test_the_event_stream_is_the_step_log_framed_by_the_run_and_its_stop(tmp_path: Path,
                                                                          bench_profile_path: Path) -> None:
    reader, writer = os.pipe()
    process = _run(tmp_path, bench_profile_path, "--events", str(writer), pass_fds=(writer,))
    os.close(writer)
    with open(reader, encoding="utf-8") as stream:
        events = [json.loads(line) for line in stream]
    output, _ = process.communicate(timeout=120)
    assert process.returncode == 0, output
    (folder,) = (tmp_path / "runs").iterdir()
    record = json.loads((folder / "run.json").read_text())
    logged = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    assert events[0] == {"event": "run", "folder": str(folder.resolve()), "steps": len(record["plan"]),
                         "todo": len(record["plan"]), "resumed": False}
    assert events[1:-1] == logged  # every step-log event, as written, in order
    assert [e["step"] for e in logged if e["event"] == "done"] == record["plan"]
    assert events[-1] == {"event": "stop", **record["stop"]} and record["stop"]["status"] == "finished"


@pytest.mark.slow
def test_a_reader_that_goes_away_stops_the_stream_not_the_run(tmp_path: Path, bench_profile_path: Path) -> None:
    reader, writer = os.pipe()
    process = _run(tmp_path, bench_profile_path, "--events", str(writer), pass_fds=(writer,))
    os.close(writer)
    with open(reader, encoding="utf-8") as stream:
        assert json.loads(stream.readline())["event"] == "run"
    output, _ = process.communicate(timeout=120)  # the pipe has no reader left: writing to it fails in the run
    assert process.returncode == 0, output
    (folder,) = (tmp_path / "runs").iterdir()
    assert json.loads((folder / "run.json").read_text())["stop"]["status"] == "finished"


def test_events_to_a_descriptor_that_is_not_open_is_one_line(tmp_path: Path, bench_profile_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    procedure = tmp_path / "sweep.toml"
    procedure.write_text(POWER_SWEEP)
    line = one_error_line(capsys, ["run", str(procedure), "--profile", str(bench_profile_path), "--out",
                                   str(tmp_path / "runs"), "--events", "97"])
    assert line.endswith("--events 97: not an open file descriptor (Bad file descriptor)")
    assert not (tmp_path / "runs").exists()  # refused before anything was created


def test_a_resumed_run_says_so_and_how_much_is_left(tmp_path: Path, bench_profile_path: Path) -> None:
    from benchctl.runner.engine import run_procedure

    procedure = tmp_path / "says.py"
    procedure.write_text("from benchctl.runner.api import Parameters, Step\n\nDESCRIPTION = 'two quick steps'\n"
                         "PARAMETERS = Parameters\n\n\ndef plan(context):\n"
                         "    return [Step(key, key, lambda context: {}) for key in ('one', 'two')]\n")
    first: list[dict] = []
    done = run_procedure(procedure, profile=str(bench_profile_path), out=tmp_path / "runs", events=first.append,
                         say=lambda line: None)
    assert [(e["event"], e.get("step")) for e in first] == [
        ("run", None), ("start", "one"), ("done", "one"), ("start", "two"), ("done", "two"), ("stop", None)]
    again: list[dict] = []
    run_procedure(None, resume=done.folder, allow_code=True, events=again.append, say=lambda line: None)
    assert again[0] == {"event": "run", "folder": str(done.folder.resolve()), "steps": 2, "todo": 0, "resumed": True}
    assert [e["event"] for e in again] == ["run", "stop"] and again[-1]["status"] == "finished"
