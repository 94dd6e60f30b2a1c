"""End-to-end tests of the `benchctl` command line on a small simulated bench."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio

from benchctl.cgh import DEFAULT_METHOD, method_names
from benchctl.cli import main


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _png(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return image


@pytest.mark.slow
def test_generate_writes_phase_pngs_reconstruction_and_metrics(capsys, tmp_path, small_profile_path):
    out = tmp_path / "gen"
    code, stdout, _ = _run(capsys, "generate", "chart:bars", "--profile", str(small_profile_path), "-o", str(out))
    assert code == 0
    for colour in ("red", "green", "blue"):
        phase = _png(out / f"phase_{colour}.png")
        assert phase.shape == (64, 96) and phase.dtype == np.uint8
        assert len(np.unique(phase)) > 16  # a real phase pattern, not a constant
    assert _png(out / "reconstruction.png").shape == (48, 80, 3)
    assert _png(out / "target.png").shape == (48, 80, 3)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "dpac" and metrics["grid"] == [64, 96] and metrics["roi"] == [48, 80]
    # DPAC of the bars on this bench, as measured (deterministic; the tolerance covers FFT rounding across CPUs)
    for colour, psnr_db, ssim in (("red", 18.59, 0.420), ("green", 18.70, 0.280), ("blue", 17.49, 0.616)):
        entry = metrics["colours"][colour]
        assert entry["skipped"] is False and entry["seconds"] > 0
        assert entry["psnr_amplitude_db"] == pytest.approx(psnr_db, abs=0.02), colour
        assert entry["ssim_amplitude"] == pytest.approx(ssim, abs=0.002), colour
    assert metrics["merged"]["psnr_srgb_db"] == pytest.approx(18.75, abs=0.02)
    # the PNGs written score what metrics.json says, by scikit-image's PSNR (8-bit rounding moves it < 0.01 dB)
    written = peak_signal_noise_ratio(_png(out / "target.png"), _png(out / "reconstruction.png"), data_range=255)
    assert written == pytest.approx(metrics["merged"]["psnr_srgb_db"], abs=0.01)
    assert "merged: PSNR 18.75 dB sRGB" in stdout


def test_generate_skips_colours_black_in_target(capsys, tmp_path, small_profile_path):
    image = np.zeros((40, 60, 3), np.uint8)
    image[10:30, 15:45, 1] = 255  # pure green square (OpenCV order is BGR: index 1 is green either way)
    target = tmp_path / "green.png"
    cv2.imwrite(str(target), image)
    out = tmp_path / "gen"
    code, stdout, _ = _run(capsys, "generate", str(target), "-p", str(small_profile_path), "-o", str(out))
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["colours"]["red"] == {"wavelength_nm": 680, "skipped": True}
    assert metrics["colours"]["blue"]["skipped"] is True
    assert metrics["colours"]["green"]["skipped"] is False
    assert sorted(p.name for p in out.glob("phase_*.png")) == ["phase_green.png"]
    assert "red: skipped" in stdout


@pytest.mark.slow
def test_generate_is_deterministic_for_a_seed(capsys, tmp_path, small_profile_path):
    outs = []
    for name in ("a", "b", "c"):
        seed = "7" if name != "c" else "8"
        args = ["generate", "chart:siemens", "-m", "gs", "-n", "3", "--colours", "green", "--seed", seed,
                "-p", str(small_profile_path), "-o", str(tmp_path / name)]
        assert _run(capsys, *args)[0] == 0
        outs.append((tmp_path / name / "phase_green.png").read_bytes())
    assert outs[0] == outs[1]
    assert outs[0] != outs[2]


@pytest.mark.parametrize(
    "args, message",
    [
        (["generate", "missing.png", "-o", "{tmp}/o"], "missing.png"),
        (["generate", "chart:nope", "-o", "{tmp}/o"], "chart:nope"),
        (["generate", "chart:bars", "--colours", "purple", "-o", "{tmp}/o"], "purple"),
        (["generate", "chart:bars", "-o", "{tmp}/afile/o"], "afile"),
        (["generate", "chart:bars", "--profile", "{tmp}/nope.toml", "-o", "{tmp}/o"], "nope.toml"),
        (["profile", "check", "{tmp}/bad.toml"], "slm.pitch_um"),
    ],
)
def test_user_errors_are_one_line_and_exit_nonzero(capsys, tmp_path, small_profile_path, args, message):
    (tmp_path / "afile").write_text("not a folder")
    (tmp_path / "bad.toml").write_text(small_profile_path.read_text().replace("pitch_um = 8.0", "pitch_um = -1"))
    argv = [a.replace("{tmp}", str(tmp_path)) for a in args]
    if "--profile" not in argv and argv[0] == "generate":
        argv += ["--profile", str(small_profile_path)]
    code, _, err = _run(capsys, *argv)
    assert code == 2
    assert err.startswith("benchctl: error:") and err.count("\n") == 1
    assert message in err


@pytest.mark.parametrize("method", ["magic", "dpac+sgd", "holonet-dcm4+gs"])
def test_unknown_method_is_one_line_listing_every_method(capsys, tmp_path, method):
    assert main(["generate", "chart:bars", "--method", method, "-o", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"unknown hologram method {method!r}" in err
    assert "dpac, gs, sgd" in err and "holonet-dcm4" in err and "<learned>+sgd" in err
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_generate_takes_iterations_from_zero_and_the_procedures_default_method(capsys, tmp_path, small_profile_path):
    """--iterations has the bound procedures and methods have (>= 0: SGD at 0 is its start, the DPAC hologram),
    and --method the default they have (cgh.DEFAULT_METHOD)."""
    profile = ["chart:bars", "--profile", str(small_profile_path), "--colours", "green"]
    assert _run(capsys, "generate", *profile, "-m", "sgd", "-n", "0", "-o", str(tmp_path / "sgd0"))[0] == 0
    assert _run(capsys, "generate", *profile, "-o", str(tmp_path / "default"))[0] == 0
    assert json.loads((tmp_path / "default" / "metrics.json").read_text())["method"] == DEFAULT_METHOD == "dpac"
    assert np.array_equal(_png(tmp_path / "sgd0" / "phase_green.png"), _png(tmp_path / "default" / "phase_green.png"))
    with pytest.raises(SystemExit):
        main(["generate", *profile, "-n", "-1", "-o", str(tmp_path / "x")])
    assert "argument --iterations/-n: must be >= 0, got -1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["generate", "--help"])
    assert f"(default: {DEFAULT_METHOD}, as in procedures;" in " ".join(capsys.readouterr().out.split())


@pytest.mark.slow  # takes seconds to a minute on two cores
def test_console_script_reports_errors_without_traceback(tmp_path):
    result = subprocess.run([sys.executable, "-m", "benchctl", "generate", str(tmp_path / "none.png"), "-o",
                             str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert "none.png" in result.stderr


def test_profile_check_describes_the_default_profile(capsys):
    code, stdout, _ = _run(capsys, "profile", "check", "simulated")
    assert code == 0
    assert "3.74" in stdout and "680" in stdout and "OK" in stdout


def test_targets_lists_the_bundled_charts(capsys):
    code, stdout, _ = _run(capsys, "targets")
    assert code == 0
    for name in ("chart:siemens", "chart:bars", "chart:wedge", "chart:text"):
        assert name in stdout


@pytest.mark.slow  # takes seconds to a minute on two cores
def test_bench_speed_vs_error_writes_a_row_per_method_budget_and_target(capsys, tmp_path, small_profile_path):
    out = tmp_path / "bench"
    code, stdout, _ = _run(capsys, "bench", "speed-vs-error", "--size", "32x48", "--methods", "dpac,gs",
                           "--iterations", "2,4", "--targets", "chart:siemens", "chart:bars",
                           "-p", str(small_profile_path), "-o", str(out))
    assert code == 0
    with open(out / "speed_vs_error.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["method"], r["iterations"]) for r in rows] == [
        ("dpac", ""), ("dpac", ""), ("gs", "2"), ("gs", "2"), ("gs", "4"), ("gs", "4")]
    assert all(float(r["seconds_per_frame"]) > 0 and np.isfinite(float(r["psnr_srgb_db"])) for r in rows)
    assert (out / "speed_vs_error.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "s/frame" in stdout and "Pareto front" in stdout
    with open(out / "front.csv") as handle:
        front = list(csv.DictReader(handle))
    assert [(r["method"], r["iterations"]) for r in front] == [("dpac", ""), ("gs", "2"), ("gs", "4")]
    assert {r["front"] for r in front} <= {"True", "False"} and "True" in {r["front"] for r in front}
    code, _, stderr = _run(capsys, "bench", "speed-vs-error", "--full", "--size", "32x48", "-p",
                           str(small_profile_path))
    assert code != 0 and "--full" in stderr and len(stderr.strip().splitlines()) == 1


def test_models_lists_every_registered_method_with_parameter_counts(capsys):
    code, stdout, _ = _run(capsys, "models", "--size", "1088x1920")
    assert code == 0
    rows = {line.split()[0]: line for line in stdout.splitlines()[2:]}
    assert list(rows) == method_names()
    assert "2,868,466" in rows["holonet"] and "3,111,952" in rows["holonet-dcm4"]
    assert "3,111,952" in rows["holonet-dcm4+sgd"]  # the network it refines
    assert "yes" in rows["sgd"] and "no trained checkpoint" in rows["holonet"] and "no trained" in rows["holonet+sgd"]
