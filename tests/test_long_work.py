"""Long work says how long and how much: the dry run prints a time and disk estimate from the plan (a first colour
capture on the simulated EOS M10 keeps 72 RAW frames, 2.7 GB), a run refuses in one line to start on a disk without
the room, every step's line says how much time is left, and an error in a procedure's values names its file and key."""

from __future__ import annotations

import re
from collections import namedtuple
from pathlib import Path

import pytest

from benchctl.cli import main
from benchctl.memory import exposure_estimate
from benchctl.profiles import load_profile
from benchctl.runner import estimates
from benchctl.runner.engine import run_procedure

REPO = Path(__file__).resolve().parents[1]


def test_the_dry_run_of_a_first_colour_capture_says_its_time_and_disk(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """The shipped procedure on the shipped simulated profile, nothing calibrated: lookup tables (3 x 17 frames),
    registration (3 x 3), probes (3) and captures (3 x 3) keep 72 RAW frames of 37.3 MB."""
    assert main(["run", str(REPO / "procedures" / "colour_capture.toml"), "--dry-run", "--out",
                 str(tmp_path / "runs")]) == 0
    out = capsys.readouterr().out
    time_line = next(line for line in out.splitlines() if line.startswith("time: about "))
    disk_line = next(line for line in out.splitlines() if line.startswith("disk: about "))
    assert "(72 frame(s) at about 3.0 s each with the simulated camera's 18.6 Mpx" in time_line, time_line
    minutes = re.match(r"time: about (\d+) min", time_line)
    assert minutes and 3 <= int(minutes[1]) <= 4, time_line  # the README's first run: 3 min 43 s
    expected = f"disk: about 2.95 GB in {tmp_path / 'runs'} (72 RAW frame(s) of 37.3 MB kept"
    assert disk_line.startswith(expected), disk_line
    assert not (tmp_path / "runs").exists()


def test_the_dry_run_estimates_a_genicam_camera_by_its_region_and_pixel_format(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The example GenICam profile with its region line filled in (2048 x 2048 BayerRG12): time, disk and memory
    rest on that region (8.39 MB a DNG, 12-bit samples over GigE Vision), not on the simulated EOS M10's 37.3 MB
    (2.95 GB for this run: refused on a disk with 1 GB free)."""
    text = (REPO / "hardware_profiles" / "genicam_hdmi.toml").read_text()
    assert "# region = [0, 0, 2048, 2048] " in text
    profile = tmp_path / "lab.toml"
    profile.write_text(text.replace("# region = [0, 0, 2048, 2048] ", "region = [0, 0, 2048, 2048]   "))
    assert main(["run", str(REPO / "procedures" / "colour_capture.toml"), "--profile", str(profile), "--dry-run",
                 "--out", str(tmp_path / "runs")]) == 0
    lines = capsys.readouterr().out.splitlines()
    time_line, disk_line, memory_line = (next(line for line in lines if line.startswith(start))
                                         for start in ("time: about ", "disk: about ", "memory: about "))
    # 72 frames of 10 ms exposure + 4.19 Mpx x 2 bytes over 100 MB/s, a 150 ms settle per exposure, 14 one-second steps
    assert time_line.startswith("time: about 30 s (72 frame(s) at about 0.1 s each with camera genicam's 4.19 Mpx "
                                "region (2048 x 2048 BayerRG12), 14 other step(s)"), time_line
    assert disk_line.startswith(f"disk: about 664 MB in {tmp_path / 'runs'} (72 RAW frame(s) of 8.39 MB kept, "), \
        disk_line
    assert memory_line.startswith("memory: about "), memory_line  # its peak is the hologram step's here
    exposure = exposure_estimate(load_profile(profile), 2, 1)
    assert exposure.what == "an exposure of RAW frames of 2048 x 2048 px (9.23 MB held per frame)", exposure.what


def test_a_run_refuses_to_start_on_a_disk_without_room(tmp_path: Path, bench_profile_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(estimates.shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 10**5, 10**5))
    procedure = tmp_path / "capture.toml"
    procedure.write_text('procedure = "colour-capture"\n[parameters]\nlut_calibration = "skip"\n')
    assert main(["run", str(procedure), "--profile", str(bench_profile_path), "--out", str(tmp_path / "runs")]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"benchctl: error: {tmp_path / 'runs'}: 100 kB free, and this run keeps about ") and (
        "free some space (benchctl runs remove ...) or write the run elsewhere (--out DIR)" in line), line
    assert not (tmp_path / "runs").exists()


@pytest.mark.slow
def test_every_step_says_how_much_time_is_left(tmp_path: Path, bench_profile_path: Path) -> None:
    procedure = tmp_path / "capture.toml"
    procedure.write_text('procedure = "colour-capture"\n[parameters]\nlut_calibration = "skip"\nexposure = "fixed"\n')
    said: list[str] = []
    run_procedure(procedure, profile=str(bench_profile_path), out=tmp_path / "runs", say=said.append)
    steps = [line for line in said if line.startswith("[")]
    assert len(steps) == 17 and all(re.match(r"\[\d+/17, about (\d+ s|\d+ min \d\d s) left\] ", line)
                                    for line in steps), steps
    assert steps[-1].startswith("[17/17, about ") and "report.html" in steps[-1]


@pytest.mark.parametrize("value, key", [('targets = ["photo:coffe"]', "parameters.targets: unknown photo"),
                                        ('colours = ["gren"]', "parameters.colours: "),
                                        ('setpoints = { red = "500mW" }', "parameters.setpoints.red: 500 mW")])
def test_an_error_in_a_procedures_values_names_the_file_and_the_key(tmp_path: Path, bench_profile_path: Path,
                                                                    value: str, key: str,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    procedure = tmp_path / "capture.toml"
    procedure.write_text(f'procedure = "colour-capture"\n[parameters]\n{value}\n')
    assert main(["run", str(procedure), "--profile", str(bench_profile_path), "--dry-run"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"benchctl: error: {procedure}: {key}"), line
