"""The first hour: values typed the way people type them are read, misspelt names get a suggestion, `--help`
explains every command, device commands print numbers for people, and a RAW frame can be looked at without Python."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import one_error_line

from benchctl.cli import main
from benchctl.dng import dng_bytes
from benchctl.images import read_image
from benchctl.runner.procedure import BUILTINS

REPO = Path(__file__).resolve().parents[1]


def test_a_power_in_two_words_is_read(capsys: pytest.CaptureFixture[str], small_profile_path: Path) -> None:
    assert main(["laser", "set", "red", "20", "mW", "-p", str(small_profile_path)]) == 0
    assert capsys.readouterr().out == "red: setpoint 20 mW (read back)\n"


@pytest.mark.parametrize("power, problem", [("-5mW", "is negative"), ("-.5 W", "is negative"),
                                            ("-5", "has no unit (W, mW or %?)")])
def test_a_negative_power_is_refused_as_negative_not_as_a_missing_argument(
        power: str, problem: str, capsys: pytest.CaptureFixture[str], small_profile_path: Path) -> None:
    line = one_error_line(capsys, ["laser", "set", "red", *power.split(), "-p", str(small_profile_path)])
    assert line.startswith(f"benchctl: error: power {power!r} {problem}")


def test_a_file_that_is_no_profile_is_named_as_such(capsys: pytest.CaptureFixture[str], in_repo: None) -> None:
    for name in ("README.md", "Makefile"):
        line = one_error_line(capsys, ["laser", "status", "-p", name])
        assert line.startswith(f"benchctl: error: {name}: not a hardware profile (a TOML file such as "
                               "hardware_profiles/simulated.toml): Expected '=' after a key"), line


@pytest.fixture
def in_repo(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)


@pytest.mark.parametrize("argv, message", [
    (["chart:bars", "-m", "dpca"], "unknown hologram method 'dpca' (did you mean 'dpac'?); known: dpac, gs, sgd;"),
    (["chart:bars", "-m", "ccnn-dcm4+sdg"], "unknown hologram method 'ccnn-dcm4+sdg' (did you mean 'ccnn-dcm4+sgd'?)"),
    (["photo:coffe"], "unknown photo 'photo:coffe' (did you mean 'photo:coffee'?); known photos: photo:astronaut,"),
    (["chart:bar"], "unknown chart 'chart:bar' (did you mean 'chart:bars'?); known charts: chart:siemens,"),
    (["coffee"], "coffee: no such file or target (did you mean 'photo:coffee'?)"),
    (["chart:star"], "unknown chart 'chart:star'; known charts: chart:siemens,"),  # nothing close: no guess
])
def test_a_misspelt_method_or_target_gets_a_suggestion(argv: list[str], message: str, tmp_path: Path,
                                                        small_profile_path: Path, in_repo: None,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    line = one_error_line(capsys, ["generate", *argv, "-o", str(tmp_path / "g"), "-p", str(small_profile_path)])
    assert line.startswith(f"benchctl: error: {message}")


def test_a_misspelt_method_in_a_procedure_gets_a_suggestion(tmp_path: Path, bench_profile_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    procedure = tmp_path / "p.toml"
    procedure.write_text('procedure = "colour-capture"\n[parameters]\nmethod = "dpca"\n')
    line = one_error_line(capsys, ["run", str(procedure), "-p", str(bench_profile_path), "--dry-run"])
    assert "unknown hologram method 'dpca' (did you mean 'dpac'?)" in line


@pytest.mark.parametrize("argv, message", [
    (["console", "--port", "99999"], "argument --port: must lie between 0 and 65535, got 99999"),
    (["console", "--deadman", "inf"], "argument --deadman: must be a finite number of seconds above 0, got 'inf'"),
    (["console", "--deadman", "0"], "argument --deadman: must be a finite number of seconds above 0, got '0'"),
    (["console", "--deadman", "1e9"], "argument --deadman: must be at most 300 seconds (a dead-man switch that "
                                      "waits longer guards nothing), got '1e9'"),
    (["bench", "console", "--seconds", "-1"],
     "argument --seconds: must be a finite number of seconds above 0, got '-1'"),
])
def test_console_times_and_ports_out_of_range_are_usage_errors(argv: list[str], message: str,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """An endless dead-man would never switch the laser off; these were tracebacks or accepted before."""
    with pytest.raises(SystemExit) as done:
        main(argv)
    assert done.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1].endswith(f"error: {message}")


def help_text(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    with pytest.raises(SystemExit) as done:
        main([*argv, "--help"])
    assert done.value.code == 0
    return " ".join(capsys.readouterr().out.split())  # argparse wraps lines where it likes


def test_help_lists_every_procedure_and_describes_every_device(capsys: pytest.CaptureFixture[str]) -> None:
    top = help_text(capsys)
    assert all(kind in top for kind in BUILTINS), top
    assert "The phase SLM the profile describes." in help_text(capsys, "slm")
    assert "The camera the profile describes." in help_text(capsys, "camera")
    assert "camera: info, capture RAW frames, show one" in top


def test_device_commands_print_numbers_for_people(capsys: pytest.CaptureFixture[str],
                                                   small_profile_path: Path) -> None:
    p = str(small_profile_path)
    assert main(["laser", "set", "blue", "33.96mW", "-p", p]) == 0
    assert main(["slm", "info", "-p", p]) == 0
    assert main(["sim", "status"]) == 0
    out = capsys.readouterr().out
    for python in ("{", "[", "'", "True", "False", "0.0339600", "_w"):
        assert python not in out, python
    assert "shape: 64, 96\n" in out and "flip_x: no\n" in out and "settle_ms: 100\n" in out
    assert "luts: red linear, 2 pi = gray 256; green linear, 2 pi = gray 256; blue linear, 2 pi = gray 256\n" in out
    assert "  rgb-laser:\n" in out and "      3: setpoint 33.96 mW; emission no\n" in out


def write_frame(path: Path) -> Path:
    """A 22 x 30 RGGB frame (black 100, white 4095; LibRaw reads none much smaller) with 2 px of margin at the top
    and left: red at 50 % with one clipped pixel, greens at 25 %, blue at 10 %."""
    raw = np.full((24, 32), 100, np.uint16)
    visible = raw[2:, 2:]
    visible[0::2, 0::2] = 100 + 1998
    visible[0, 0] = 4095
    visible[0::2, 1::2] = visible[1::2, 0::2] = 100 + 999
    visible[1::2, 1::2] = 100 + 400
    path.write_bytes(dng_bytes(raw, cfa="RGGB", black_level=100, white_level=4095, active_area=(2, 2, 24, 32)))
    return path


def test_camera_show_describes_a_monochrome_frame(tmp_path: Path, in_repo: None,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A mono sensor's frame: every colour reads every pixel (it divided by zero reading none before)."""
    raw = np.full((24, 32), 100, np.uint16)
    raw[2:, 2:] = 100 + 1998
    raw[2, 2] = 4095
    frame = tmp_path / "mono.dng"
    frame.write_bytes(dng_bytes(raw, cfa=None, black_level=100, white_level=4095, active_area=(2, 2, 24, 32)))
    assert main(["camera", "show", str(frame), "-o", str(tmp_path / "look.png")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"{frame}: 30 x 22 px visible (width x height), monochrome (every colour reads every pixel)"
    for colour, line in zip(("  red", "green", " blue"), lines[2:5]):  # mean (659 x 1998 / 3995 + 1) / 660
        # the 99.9th percentile of 659 pixels at 50.01 % and one at 100 %: 0.341 of the way up (numpy's interpolation)
        assert line == (f"{colour}: peak 67.1% of full scale (brightest 0.1 %), brightest pixel 100.0%, mean 50.09%, "
                        "saturated 0.152% (1 of 660 px)")


def test_camera_show_describes_a_raw_frame_and_writes_a_preview(tmp_path: Path, in_repo: None,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    frame = write_frame(tmp_path / "frame.dng")
    preview = tmp_path / "look.png"
    assert main(["camera", "show", str(frame), "-o", str(preview)]) == 0
    assert capsys.readouterr().out.splitlines() == [
        f"{frame}: 30 x 22 px visible (width x height), RGGB Bayer",
        "black level 100, 100, 100, 100 (per CFA position, RGGB), white level 4095",
        # mean (164 x 1998/3995 + 1) / 165; peak 0.836 of the way from 50.01 % to 100 % (99.9th percentile of 165)
        "  red: peak 91.8% of full scale (brightest 0.1 %), brightest pixel 100.0%, mean 50.32%, saturated 0.606% "
        "(1 of 165 px)",
        "green: peak 25.0% of full scale (brightest 0.1 %), brightest pixel 25.0%, mean 25.01%, saturated 0.000% "
        "(0 of 330 px)",
        " blue: peak 10.0% of full scale (brightest 0.1 %), brightest pixel 10.0%, mean 10.01%, saturated 0.000% "
        "(0 of 165 px)",
        f"preview: {preview} (15 x 11 px, amplitude: square root of the signal, the frame's brightest pixel white)"]
    image = read_image(preview)
    assert image.shape == (11, 15, 3) and image.dtype == np.uint8
    assert tuple(image[0, 0]) == (255, 128, 81) and tuple(image[1, 1]) == (180, 128, 81)  # sqrt(0.5) = 0.707


def test_camera_show_needs_no_profile_camera_or_torch(tmp_path: Path) -> None:
    frame = write_frame(tmp_path / "frame.dng")
    probe = ("import json, sys\nfrom benchctl.cli import main\ncode = main(sys.argv[1:])\n"
             "print(json.dumps([code, [m for m in ('torch', 'benchctl.optics.propagation') if m in sys.modules]]))")
    done = subprocess.run([sys.executable, "-c", probe, "camera", "show", str(frame)], capture_output=True,
                          text=True, timeout=120, check=True, cwd=tmp_path)
    assert json.loads(done.stdout.splitlines()[-1]) == [0, []]
    assert (tmp_path / "frame.dng.preview.png").is_file()


def test_camera_show_of_a_file_that_is_no_raw_is_one_line(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    text = tmp_path / "notes.dng"
    text.write_text("not a raw file")
    assert one_error_line(capsys, ["camera", "show", str(text)]).startswith(
        f"benchctl: error: cannot decode RAW file {text}: ")
