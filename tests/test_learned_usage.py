"""Trained checkpoints in use: generate, compute_scene, shipped-checkpoint lookup, models, and the benchmarks."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import SMALL_PROFILE

from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.setups import optical_setup
from benchctl.cgh import OpticalSetup
from benchctl.cgh.learned import model_info
from benchctl.cli import main
from benchctl.devices.slm import slm_for
from benchctl.errors import BenchctlError
from benchctl.holograms.checkpoints import find_checkpoint, learned_method
from benchctl.holograms.scene import compute_scene
from benchctl.profiles import load_profile
from benchctl.targets import load_target, prepare_target
from benchctl.training.training import TrainSettings, train


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(small profile, a ccnn-dcm4 checkpoint for it trained for a few steps and stored as float16)."""
    folder = tmp_path_factory.mktemp("trained")
    profile_path = folder / "small.toml"
    profile_path.write_text(SMALL_PROFILE)
    settings = TrainSettings(method="ccnn-dcm4", data="procedural:3", epochs=1, lr=1e-3, weights_dtype="float16")
    result = train(load_profile(profile_path), settings, folder / "ckpt", {"red": 0, "green": 1, "blue": 2},
                   out=lambda _: None)
    assert result.checkpoint is not None
    return profile_path, result.checkpoint


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_generate_with_a_checkpoint_writes_the_trained_models_holograms(capsys, tmp_path, trained) -> None:
    profile_path, checkpoint = trained
    out = tmp_path / "gen"
    code, stdout, err = _run(capsys, "generate", "chart:bars", "--method", "ccnn-dcm4", "--checkpoint",
                             str(checkpoint), "-p", str(profile_path), "-o", str(out))
    assert code == 0, err
    assert f"trained models from {checkpoint}" in stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "ccnn-dcm4" and metrics["checkpoint"] == str(checkpoint)
    assert metrics["iterations"] is None
    # The displayed frame is exactly the network's phase for that colour, encoded for the SLM.
    profile = load_profile(profile_path)
    target = prepare_target(load_target("chart:bars", profile.optics.roi), profile.slm.shape, profile.optics.roi)
    setup = optical_setup(profile, "green")
    phase = learned_method("ccnn-dcm4", checkpoint)(target[1], setup)
    expected = slm_for(profile).encode(phase, "green")
    written = cv2.imread(str(out / "phase_green.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(written, expected)
    assert len(np.unique(written)) > 16


@pytest.mark.parametrize("method, data", [("holonet-dcm4", "DIR"), ("holonet3d-dcm4", "procedural-rgbd:1024")])
def test_learned_method_without_a_checkpoint_is_a_clear_error(capsys, tmp_path, small_profile_path, method,
                                                              data) -> None:
    code, _, err = _run(capsys, "generate", "chart:bars", "--method", method, "-p", str(small_profile_path),
                        "-o", str(tmp_path / "gen"))
    assert code == 2
    assert f"no trained checkpoint for '{method}' and profile 'small'" in err
    assert f"benchctl train --method {method} --data {data} --profile small`" in err and "--checkpoint" in err
    assert "Traceback" not in err and not (tmp_path / "gen" / "metrics.json").exists()


def test_checkpoint_misuse_is_refused(capsys, tmp_path, trained) -> None:
    profile_path, checkpoint = trained
    code, _, err = _run(capsys, "generate", "chart:bars", "--method", "dpac", "--checkpoint", str(checkpoint),
                        "-p", str(profile_path), "-o", str(tmp_path / "a"))
    assert code == 2 and "'dpac' is not a learned method and takes no checkpoint" in err
    code, _, err = _run(capsys, "generate", "chart:bars", "--method", "ccnn-dcm4", "-n", "5", "--checkpoint",
                        str(checkpoint), "-p", str(profile_path), "-o", str(tmp_path / "b"))
    assert code == 2 and "one-shot and takes no iteration count" in err
    code, _, err = _run(capsys, "generate", "chart:bars", "--method", "ccnn-dcm4", "--checkpoint", str(checkpoint),
                        "-o", str(tmp_path / "c"))  # the default, simulated profile
    assert code == 2
    assert "pitch 8 um in the checkpoint, 3.74 um in profile 'simulated'" in err
    assert "grid 64x96 in the checkpoint, 1088x1920 in profile 'simulated'" in err


def test_a_learned_method_serves_only_the_setups_it_was_trained_for(trained) -> None:
    profile_path, checkpoint = trained
    method = learned_method("ccnn-dcm4", checkpoint)
    setup = optical_setup(load_profile(profile_path), "red")
    other = OpticalSetup(wavelength_m=633e-9, pitch_m=setup.pitch_m, distance_m=setup.distance_m, shape=setup.shape,
                         roi=setup.roi, padding=setup.padding, aperture=setup.aperture)
    target = torch.zeros(setup.shape)
    target[setup.roi_slices] = 1.0
    assert method(target, setup).shape == setup.shape
    with pytest.raises(BenchctlError, match="nearest is red: wavelength 680 nm in the checkpoint, 633 nm in this"):
        method(target, other)


@pytest.mark.slow
def test_shipped_checkpoint_is_found_listed_and_used_by_default(capsys, tmp_path, monkeypatch, trained) -> None:
    profile_path, checkpoint = trained
    monkeypatch.chdir(tmp_path)
    profile = load_profile(profile_path)
    assert find_checkpoint("ccnn-dcm4", profile) is None
    shipped = Path("checkpoints/small/ccnn-dcm4.pt")
    shipped.parent.mkdir(parents=True)
    shutil.copy(checkpoint, shipped)
    assert find_checkpoint("ccnn-dcm4", profile) == shipped and find_checkpoint("ccnn", profile) is None

    code, stdout, _ = _run(capsys, "models", "-p", str(profile_path))
    assert code == 0
    rows = {line.split()[0]: line for line in stdout.splitlines()[2:]}
    assert f"yes ({shipped}; BELOW DPAC on its validation images (red " in rows["ccnn-dcm4"]  # a 1-step training
    assert "no (no trained checkpoint for profile 'small')" in rows["ccnn"]
    assert f"{model_info('ccnn-dcm4', (64, 96))['parameters']:,}" in rows["ccnn-dcm4"]

    target = prepare_target(load_target("chart:siemens", profile.optics.roi), profile.slm.shape, profile.optics.roi)
    scene = compute_scene(target, Calibrated(profile), "ccnn-dcm4", colours=["blue"])
    assert scene.checkpoint == shipped and not scene.colours[0].skipped

    out = tmp_path / "bench"
    code, stdout, _ = _run(capsys, "bench", "speed-vs-error", "--size", "64x96", "--iterations", "2", "--targets",
                           "chart:siemens", "-p", str(profile_path), "-o", str(out))
    assert code == 0
    with open(out / "speed_vs_error.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["method"], r["iterations"]) for r in rows] == [
        ("dpac", ""), ("gs", "2"), ("sgd", "2"), ("ccnn-dcm4", ""), ("ccnn-dcm4+sgd", "2")]
    code, stdout, _ = _run(capsys, "bench", "speed-vs-error", "--size", "32x48", "--iterations", "2", "--methods",
                           "dpac", "--targets", "chart:siemens", "-p", str(profile_path), "-o", str(out))
    assert code == 0
    code, stdout, _ = _run(capsys, "bench", "speed-vs-error", "--size", "32x48", "--iterations", "2", "--targets",
                           "chart:siemens", "-p", str(profile_path), "-o", str(out))
    assert "not running ccnn-dcm4" in stdout and "grid 64x96 in the checkpoint, 32x48" in stdout


@pytest.mark.slow
def test_bench_learned_measures_side_by_side_with_ratios(capsys, tmp_path, trained) -> None:
    profile_path, checkpoint = trained
    out = tmp_path / "bench"
    code, stdout, err = _run(capsys, "bench", "learned", "--methods", "ccnn-dcm4", "--checkpoint", str(checkpoint),
                             "--repeats", "1", "-p", str(profile_path), "-o", str(out))
    assert code == 0, err
    header = next(line for line in stdout.splitlines() if line.startswith("method"))
    for column in ("params", "x params", "s/frame", "speed-up", "train MiB", "mem -%", "PSNR amp", "SSIM amp"):
        assert column in header
    assert "adding the baseline network(s) ccnn" in stdout and "VmHWM" in stdout
    with open(out / "learned.csv") as handle:
        rows = {r["method"]: r for r in csv.DictReader(handle)}
    assert set(rows) == {"ccnn", "ccnn-dcm4"}
    base, dcm = rows["ccnn"], rows["ccnn-dcm4"]
    assert int(base["parameters"]) == 42_260
    assert int(dcm["parameters"]) == model_info("ccnn-dcm4", (64, 96))["parameters"]
    assert float(base["speedup"]) == 1.0 and float(base["memory_reduction_pct"]) == 0.0
    assert float(dcm["speedup"]) == pytest.approx(float(base["inference_seconds"]) / float(dcm["inference_seconds"]))
    assert float(dcm["parameters_ratio"]) == pytest.approx(int(dcm["parameters"]) / 42_260)
    assert float(base["train_step_peak_mib"]) > 0 and float(dcm["train_step_peak_mib"]) > 0
    assert 0 < float(dcm["psnr_amplitude_db"]) < 100 and dcm["checkpoint"] == str(checkpoint)
    assert base["psnr_amplitude_db"] == ""  # no checkpoint for the baseline: no quality figures


@pytest.mark.slow
def test_the_memory_table_reports_a_step_above_the_cap_as_out_of_memory(capsys, tmp_path) -> None:
    """Each step runs in a subprocess whose address space is capped: one that fits gives its peak and time, one
    that does not gives a line saying so (and larger grids are not tried), never a traceback or a killed machine."""
    profile = tmp_path / "small.toml"
    profile.write_text(SMALL_PROFILE)
    code, stdout, err = _run(capsys, "bench", "learned", "--grids", "32x48", "64x96", "--methods", "ccnn",
                             "--memory-cap", "8", "-p", str(profile), "-o", str(tmp_path / "ok"))
    assert code == 0, err
    rows = list(csv.DictReader((tmp_path / "ok" / "learned_memory.csv").open()))
    assert [(r["grid"], r["result"]) for r in rows] == [("32x48", "ok"), ("64x96", "ok")]
    assert all(0 < float(r["peak_mib"]) < 1024 and float(r["step_seconds"]) > 0 for r in rows)
    # 1 GiB of address space is about what torch's libraries map: holonet's step at 256 x 448 cannot fit
    code, stdout, err = _run(capsys, "bench", "learned", "--grids", "512x896", "256x448", "--methods", "holonet",
                             "--memory-cap", "1", "-p", str(profile), "-o", str(tmp_path / "oom"))
    assert code == 0, err
    rows = list(csv.DictReader((tmp_path / "oom" / "learned_memory.csv").open()))
    assert [(r["grid"], r["result"]) for r in rows] == [
        ("256x448", "out of memory above 1 GiB"), ("512x896", "out of memory (at 256x448 already)")]
    assert "holonet             256x448: out of memory above 1 GiB" in stdout
