"""`benchctl run` end to end on the simulated bench: the run folder, dry run, resume, SIGTERM, bad input."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from benchctl.capture.raw import decode_raw
from benchctl.cli import main
from benchctl.devices.errors import DeviceError
from benchctl.devices.sim.state import load_state
from benchctl.errors import BenchctlError
from benchctl.images import read_image
from benchctl.profiles import load_profile
from benchctl.runner.engine import run_procedure
from benchctl.runner.plots import front_plot
from benchctl.runner.record import create_run, open_run
from benchctl.training.training import TrainSettings, train


REPO = Path(__file__).resolve().parents[1]
CAPTURE = """\
name = "capture-test"
procedure = "colour-capture"

[parameters]
targets = ["chart:bars"]
setpoints = { red = "100%", green = "100%", blue = "100%" }
frames = 2
dark_frames = 1
registration = "auto"
lut_calibration = "skip"
exposure = "fixed"
"""


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.fixture
def capture_procedure(tmp_path: Path) -> Path:
    return write(tmp_path / "capture.toml", CAPTURE)


def laser_channels() -> dict[str, dict]:
    return load_state("rgb-laser").get("channels", {})


def shutter_count() -> int:
    return int(load_state("sim-camera").get("frame", 0))


def scores(targets: list[dict]) -> list[dict]:
    """Metrics of a colour capture without the generation times (which are measured, so differ run to run)."""
    for target in targets:
        for colour in target["colours"].values():
            del colour["generation_s"], colour["cached"]
    return targets


def run_ok(procedure: Path, profile: Path, out: Path, **kwargs) -> Path:
    outcome = run_procedure(procedure, profile=str(profile), out=out, say=lambda line: None, **kwargs)
    assert outcome.folder is not None
    return outcome.folder


# -- procedure files ----------------------------------------------------------------------------------------------


def test_a_misspelt_parameter_is_named_with_a_suggestion(tmp_path: Path, bench_profile_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    bad = write(tmp_path / "bad.toml", 'procedure = "colour-capture"\n[parameters]\nframs = 2\n')
    assert main(["run", str(bad), "--profile", str(bench_profile_path), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: parameters.frams: unknown key (did you mean 'frames'?" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("text, message", [
    ('procedure = "colour-capture"\n[parameters]\nframes = "two"\n', "parameters.frames: expected an integer"),
    ('procedure = "colour-capture"\n[parameters]\nframes = 0\n', "parameters.frames: must be >= 1"),
    ('procedure = "colour-capure"\n', "unknown procedure 'colour-capure'"),
    ('name = "x"\n', "procedure: missing required key"),
    ('procedure = "colour-capture"\n[parameters]\nregistration = "maybe"\n',
     "parameters.registration: unknown value 'maybe'"),
    ('procedure = "colour-capture"\n[parameters]\nsetpoints = { red = "120%" }\n',
     "parameters.setpoints.red: 48 mW is above the channel's max_power_mw 40 mW"),
    ('procedure = "colour-capture"\n[parameters]\nsetpoints = { purple = "1mW" }\n',
     "parameters.setpoints.purple: no laser channel 'purple'"),
    ('procedure = "colour-capture"\n[parameters]\ntargets = ["chart:nope"]\n', "chart:nope"),
    ('procedure = "colour-capture"\n[parameters\n', "TOML syntax error"),
])
def test_bad_procedures_are_refused_before_anything_runs(tmp_path: Path, bench_profile_path: Path, text: str,
                                                         message: str) -> None:
    path = write(tmp_path / "p.toml", text)
    with pytest.raises(BenchctlError, match=None) as caught:
        run_procedure(path, profile=str(bench_profile_path), out=tmp_path / "runs", say=lambda line: None)
    assert message in str(caught.value)
    assert not (tmp_path / "runs").exists()
    assert laser_channels() == {}


def test_dry_run_prints_every_step_and_touches_nothing(tmp_path: Path, bench_profile_path: Path,
                                                       capture_procedure: Path, sim_state_dir: Path) -> None:
    lines: list[str] = []
    outcome = run_procedure(capture_procedure, profile=str(bench_profile_path), out=tmp_path / "runs",
                            dry_run=True, say=lines.append)
    assert outcome.folder is None
    text = "\n".join(lines)
    for key in ("registration/hologram/red", "registration/capture/blue", "registration/fit/green",
                "hologram/bars/red", "capture/bars/green", "process/bars", "report"):
        assert f". {key}: " in text
    # every exposure with its channel, power and frames, and per channel the highest power against its limit
    assert ". capture/bars/green: expose bars  [green alone at 40 mW, 2 frame(s) + 1 dark]" in text
    assert ". hologram/bars/red: hologram bars red (dpac)\n" in text  # no exposure: no device
    assert "  blue: 2 exposure(s), at most 40 mW; limit 40 mW" in lines
    assert lines[-1] == "dry run: nothing was touched"
    assert not (tmp_path / "runs").exists()
    assert list(sim_state_dir.iterdir()) == []  # no simulated device was opened
    assert not Path(os.environ["BENCHCTL_CALIBRATION_DIR"]).exists()


# -- the run folder ----------------------------------------------------------------------------------------------


def test_run_folders_are_never_reused(tmp_path: Path) -> None:
    first = create_run(tmp_path, "same name", {"procedure": "x"}, {"procedure.toml": b"a"})
    second = create_run(tmp_path, "same name", {"procedure": "x"}, {"procedure.toml": b"b"})
    assert first.folder != second.folder and first.folder.parent == second.folder.parent == tmp_path
    assert (first.folder / "procedure.toml").read_bytes() == b"a"
    assert (second.folder / "procedure.toml").read_bytes() == b"b"
    assert "same-name" in first.folder.name


def test_a_step_log_cut_by_a_crash_is_read_up_to_the_cut(tmp_path: Path) -> None:
    record = create_run(tmp_path, "r", {"procedure": "x"}, {})
    record.started("a")
    record.finished("a", 0.5, {"value": 1})
    record.started("b")
    with open(record.folder / "steps.jsonl", "a") as log:
        log.write('{"event": "done", "step": "b", "res')  # the power went out mid-line
    again = open_run(record.folder)
    assert again.done == {"a": {"value": 1}} and again.attempts == {"a": 1, "b": 1}
    assert again.info()["resumed"][0]["finished_steps"] == 1


@pytest.mark.slow
def test_colour_capture_from_a_fresh_profile(tmp_path: Path, bench_profile_path: Path,
                                             capture_procedure: Path) -> None:
    """From a fresh profile, colour capture first measures the SLM's lookup tables and registers the camera
    (neither is stored yet), then captures and scores within 2 dB of the simulated reconstruction (0.9 measured)."""
    write(capture_procedure, CAPTURE.replace('lut_calibration = "skip"', 'lut_calibration = "auto"'))
    folder = run_ok(capture_procedure, bench_profile_path, tmp_path / "runs")
    info = json.loads((folder / "run.json").read_text())
    assert info["stop"]["status"] == "finished" and info["procedure"] == "colour-capture"
    assert info["versions"]["torch"] and info["versions"]["rawpy"] != "not installed"
    assert (folder / "profile.toml").read_bytes() == bench_profile_path.read_bytes()
    assert (folder / "procedure.toml").read_bytes() == capture_procedure.read_bytes()
    devices = json.loads((folder / "devices.json").read_text())
    assert set(devices) == {"laser", "slm", "camera"} and devices["camera"]["driver"] == "sim"
    # registration ran first (none was stored) and was stored for the profile
    events = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    done = [e["step"] for e in events if e["event"] == "done"]
    assert done[0] == "lut/red/0" and done[-1] == "report" and "registration/fit/blue" in done
    for colour in ("red", "green", "blue"):  # the measured tables recover the simulated panel's true response
        fit = next(e["result"] for e in events if e["event"] == "done" and e["step"] == f"lut/{colour}/fit")
        assert fit["simulator"]["rms_rad"] < 0.05 and fit["simulator"]["max_rad"] < 0.15, (colour, fit["simulator"])
    assert {"lut-red.csv", "lut-green.csv", "lut-blue.csv", "registration.json"} <= {
        p.name for p in (Path(os.environ["BENCHCTL_CALIBRATION_DIR"]) / "bench").iterdir()}
    stored = json.loads((Path(os.environ["BENCHCTL_CALIBRATION_DIR"]) / "bench" / "registration.json").read_text())
    assert set(stored["colours"]) == {"red", "green", "blue"}
    assert not any(entry["through_model"] for entry in stored["colours"].values())  # no optical model fitted
    assert (folder / "calibration" / "registration.json").is_file()
    fits = {e["step"]: e["result"] for e in events if e["event"] == "done" and e["step"].startswith("registration/fit")}
    for fit in fits.values():
        assert fit["simulator"]["corner_error_max_px"] < 1.0
    # holograms as displayed, RAW frames as captured, 16-bit images
    hologram = read_image(folder / "holograms" / "bars-red.png")
    assert hologram.dtype == np.uint8 and hologram.shape == (128, 192)
    raw = sorted((folder / "raw" / "capture" / "bars" / "red").iterdir())
    assert [p.name for p in raw] == ["dark-000.dng", "frame-000.dng", "frame-001.dng"]
    assert decode_raw(raw[1]).mosaic.shape == (292, 428)
    capture = read_image(folder / "images" / "bars" / "capture.png")
    assert capture.dtype == np.uint16 and capture.shape == (96, 160, 3)
    # metrics and report
    metrics = json.loads((folder / "metrics.json").read_text())
    bars = metrics["targets"][0]
    simulated, captured = bars["merged"]["simulated"]["psnr_srgb_db"], bars["merged"]["capture"]["psnr_srgb_db"]
    assert captured > simulated - 2.0, (captured, simulated)
    csv_lines = (folder / "metrics.csv").read_text().splitlines()
    assert csv_lines[0].startswith("target,label,colour,generation_s") and len(csv_lines) == 1 + 3 + 1
    report = (folder / "report.html").read_text()
    for text in ("Colour capture", "merged capture", "data:image/png;base64,", "Generation time: the time it took",
                 "Calibration used", "measured 20", "capture: error against the target", "red captured (registered",
                 "SLM lookup tables", "the dots seen through the fit", "stored only if it passes its acceptance test"):
        assert text in report
    assert report.count("<svg") == 2  # the run's own tables: measured phase and zero-order signal
    assert "Generation time against error" not in report  # its numbers are in the per-colour table
    assert "not calibrated" not in report
    assert all(not state.get("emission") for state in laser_channels().values())


@pytest.mark.slow
def test_resume_after_a_pulled_cable_finishes_without_recapturing(tmp_path: Path, bench_profile_path: Path,
                                                                 capture_procedure: Path, sim_state_dir: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    reference = run_ok(capture_procedure, bench_profile_path, tmp_path / "reference")
    frames_needed = shutter_count()
    reference_metrics = json.loads((reference / "metrics.json").read_text())["targets"]

    # The same run on a fresh bench (state, calibration, cache), with the cable pulled before the 13th frame:
    # registration and the red exposure have finished by then, green fails.
    for name in ("BENCHCTL_SIM_DIR", "BENCHCTL_CALIBRATION_DIR", "BENCHCTL_CACHE_DIR"):
        monkeypatch.setenv(name, str(tmp_path / "second" / name))
    assert main(["sim", "fault", "sim-camera", "unplug_at=13"]) == 0
    with pytest.raises(DeviceError, match="cable pulled before frame 13"):
        run_ok(capture_procedure, bench_profile_path, tmp_path / "runs")
    (folder,) = (tmp_path / "runs").iterdir()
    info = json.loads((folder / "run.json").read_text())
    assert info["stop"]["status"] == "failed" and info["stop"]["step"] == "capture/bars/green"
    assert shutter_count() == 12 and all(not s.get("emission") for s in laser_channels().values())
    assert sorted(p.name for p in (folder / "raw" / "capture" / "bars" / "red").iterdir()) == [
        "dark-000.dng", "frame-000.dng", "frame-001.dng"]
    kept = {p: p.read_bytes() for p in (folder / "raw").rglob("*.dng")}

    assert main(["sim", "fault", "sim-camera", "--clear"]) == 0
    outcome = run_procedure(None, resume=folder, say=lambda line: None)
    assert outcome.folder == folder and "capture/bars/red" in outcome.skipped
    assert outcome.ran[0] == "capture/bars/green" and not any(k.startswith("registration/") for k in outcome.ran)
    assert shutter_count() == frames_needed  # nothing captured twice
    assert all(path.read_bytes() == data for path, data in kept.items())  # nothing captured was touched
    assert scores(json.loads((folder / "metrics.json").read_text())["targets"]) == scores(reference_metrics)
    info = json.loads((folder / "run.json").read_text())
    assert info["stop"]["status"] == "finished" and len(info["resumed"]) == 1
    events = [json.loads(line)["event"] for line in (folder / "steps.jsonl").read_text().splitlines()]
    assert events.count("failed") == 1
    assert "red: SLM lookup table not calibrated" in (folder / "report.html").read_text()


def test_resume_refuses_a_changed_profile(tmp_path: Path, bench_profile_path: Path, capture_procedure: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    assert main(["sim", "fault", "sim-camera", "unplug_at=2"]) == 0
    with pytest.raises(DeviceError):
        run_ok(capture_procedure, bench_profile_path, tmp_path / "runs")
    (folder,) = (tmp_path / "runs").iterdir()
    bench_profile_path.write_text(bench_profile_path.read_text().replace("distance_mm = 20.0", "distance_mm = 21.0"))
    with pytest.raises(BenchctlError, match="changed since run"):
        run_procedure(None, resume=folder, say=lambda line: None)


@pytest.mark.slow
def test_sigterm_during_a_capture_leaves_emission_off(tmp_path: Path, bench_profile_path: Path,
                                                      capture_procedure: Path) -> None:
    slow = write(tmp_path / "slow.toml", bench_profile_path.read_text() + "readout_s = 30.0\n")
    process = subprocess.Popen([sys.executable, "-m", "benchctl", "run", str(capture_procedure), "--profile",
                                str(slow), "--out", str(tmp_path / "runs")], cwd=tmp_path,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=os.environ.copy())
    deadline = time.monotonic() + 60
    while not any(s.get("emission") for s in laser_channels().values()):
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "the laser never came on"
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=30)
    assert process.returncode == 128 + signal.SIGTERM, err.decode()
    assert all(not s.get("emission") for s in laser_channels().values())
    (folder,) = (tmp_path / "runs").iterdir()
    info = json.loads((folder / "run.json").read_text())
    assert info["stop"]["status"] == "interrupted" and info["stop"]["step"] == "registration/capture/red"
    assert "--resume" in out.decode()


@pytest.mark.slow
def test_power_sweep_is_linear_and_its_exposure_advice_holds(tmp_path: Path, bench_profile_path: Path) -> None:
    sweep = write(tmp_path / "sweep.toml", 'procedure = "power-sweep"\n[parameters]\ncolours = ["red", "blue"]\n'
                  'setpoints = { red = "100%", blue = "100%" }\n')
    folder = run_ok(sweep, bench_profile_path, tmp_path / "runs")
    colours = json.loads((folder / "metrics.json").read_text())["colours"]
    red = colours["red"]
    assert red["mean_fit"]["r2"] > 0.9999 and red["mean_fit"]["max_deviation"] < 0.01
    assert [p["saturated_fraction"] for p in red["points"]] == [0.0] * 5
    # blue saturates this sensor from the second level (10 mW) on: too few levels left, and the report says so
    assert colours["blue"]["saturated_levels"] == 4 and "warning" in colours["blue"]
    assert "blue: fewer than two unsaturated levels" in (folder / "report.html").read_text()
    assert "<svg" in (folder / "report.html").read_text()
    # taking the advice: at the recommended exposure the peak at the working setpoint is 80 % of full scale
    advised = red["recommended_exposure_s"]
    profile = write(tmp_path / "advised.toml", bench_profile_path.read_text().replace(
        '[camera]\ndriver = "sim"\n', f'[camera]\ndriver = "sim"\nexposure_s = {advised!r}\n'))
    again = write(tmp_path / "again.toml", 'procedure = "power-sweep"\n[parameters]\ncolours = ["red"]\n'
                  'levels = ["50%", "100%"]\n')
    folder = run_ok(again, profile, tmp_path / "runs")
    peak = json.loads((folder / "metrics.json").read_text())["colours"]["red"]["points"][-1]["peak"]
    assert peak == pytest.approx(0.8, abs=0.02)


@pytest.mark.slow
def test_python_procedure_example_measures_the_grating_shift(tmp_path: Path, bench_profile_path: Path) -> None:
    """procedures/grating_shift.py on a calibrated bench: each colour's image moves by z lambda / (P pitch^2)."""
    for name in ("lut_calibration.toml", "registration.toml"):
        run_ok(REPO / "procedures" / name, bench_profile_path, tmp_path / "runs")
    folder = run_ok(REPO / "procedures" / "grating_shift.py", bench_profile_path, tmp_path / "runs")
    assert (folder / "grating_shift.py").read_bytes() == (REPO / "procedures" / "grating_shift.py").read_bytes()
    rows = json.loads((folder / "metrics.json").read_text())["colours"]
    for row in rows:  # 20 mm, 32 px period, 8 um pitch: 6.64 / 5.08 / 4.39 px
        expected = 0.02 * {"red": 680e-9, "green": 520e-9, "blue": 450e-9}[row["colour"]] / (32 * 8e-6 ** 2)
        assert row["predicted_px"] == pytest.approx(expected)
        # 0.35 px: the iris clips the tilted spectrum on one side, which in a noiseless model alone moves red by
        # +0.25 px more than the tilt; captures read +0.25 (OpenCV 4.14) to +0.31 px (OpenCV 5.0, whose RANSAC
        # homography differs slightly).
        assert abs(row["measured_px"] - expected) < 0.35 and abs(row["across_px"]) < 0.3, row


def test_a_python_procedure_without_plan_is_refused(tmp_path: Path, bench_profile_path: Path) -> None:
    bad = write(tmp_path / "mine.py", "PARAMETERS = {}\n")
    with pytest.raises(BenchctlError, match="must define plan"):
        run_procedure(bad, profile=str(bench_profile_path), out=tmp_path / "runs", say=lambda line: None)


def test_run_needs_a_procedure_or_a_run_to_resume(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run"]) == 2
    assert "give a procedure file" in capsys.readouterr().err
    assert main(["run", "--resume", str(tmp_path)]) == 2
    assert f"{tmp_path}: not a benchctl run folder" in capsys.readouterr().err
    assert main(["run", str(tmp_path / "missing.toml"), "--dry-run"]) == 2
    assert "missing.toml: procedure file not found" in capsys.readouterr().err


@pytest.mark.slow
def test_auto_exposure_puts_every_colours_peak_near_the_goal(tmp_path: Path, bench_profile_path: Path,
                                                              capture_procedure: Path) -> None:
    """Setpoints far too low for blue and far too high for red: one probe frame per colour sets the power so the
    registered peak lands near 70 % of full scale; the choice is in the step log, and no low-signal warning."""
    write(capture_procedure, CAPTURE.replace('exposure = "fixed"', 'exposure = "auto"').replace(
        'setpoints = { red = "100%", green = "100%", blue = "100%" }',
        'setpoints = { red = "100%", green = "10%", blue = "1%" }'))
    folder = run_ok(capture_procedure, bench_profile_path, tmp_path / "runs")
    events = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    done = {e["step"]: e["result"] for e in events if e["event"] == "done"}
    metrics = json.loads((folder / "metrics.json").read_text())["targets"][0]
    for colour, probe_mw in (("red", 40.0), ("green", 4.0), ("blue", 0.4)):
        choice = done[f"probe/bars/{colour}"]["auto_exposure"]
        assert choice["probe_w"] == pytest.approx(probe_mw * 1e-3) and choice["goal"] == 0.7
        assert not choice["probe_saturated"]
        assert done[f"capture/bars/{colour}"]["setpoint_w"] == pytest.approx(choice["power_w"], rel=1e-3)
        assert metrics["colours"][colour]["power_w"] == pytest.approx(choice["power_w"], rel=1e-3)
        peak = metrics["colours"][colour]["peak"]
        if colour == "red":  # this bench's red peaks at about 15 % even at its 40 mW maximum
            assert choice["limited_by_max"] and choice["power_w"] == pytest.approx(40e-3)
            assert peak == pytest.approx(choice["probe_peak"], rel=0.1)
        else:
            assert not choice["limited_by_max"] and choice["power_w"] > 4 * choice["probe_w"]
            assert peak == pytest.approx(0.7, abs=0.07), (colour, peak)
    assert not [w for w in metrics["warnings"] if "low signal" in w]
    assert (folder / "raw" / "probe" / "bars" / "blue" / "frame-000.dng").is_file()


@pytest.mark.slow
def test_colour_capture_with_several_methods_draws_their_front(tmp_path: Path, bench_profile_path: Path,
                                                               capture_procedure: Path) -> None:
    """method = [dpac, sgd]: each target is captured with each method under its own label; metrics.json and
    the report hold one front row per method, SGD captures better than DPAC and takes longer, so both are on
    the front, and the report plots them."""
    write(capture_procedure, CAPTURE.replace('lut_calibration = "skip"', 'lut_calibration = "auto"')
          + 'method = ["dpac", "sgd"]\niterations = 10\n')
    folder = run_ok(capture_procedure, bench_profile_path, tmp_path / "runs")
    metrics = json.loads((folder / "metrics.json").read_text())
    assert [(t["label"], t["method"]) for t in metrics["targets"]] == [("bars-dpac", "dpac"), ("bars-sgd", "sgd")]
    assert (folder / "holograms" / "bars-sgd-green.png").is_file()
    assert (folder / "raw" / "capture" / "bars-dpac" / "red").is_dir()
    front = {row["method"]: row for row in metrics["front"]}
    assert set(front) == {"dpac", "sgd"}
    dpac, sgd = front["dpac"], front["sgd"]
    captured = {t["method"]: t["merged"]["capture"]["psnr_srgb_db"] for t in metrics["targets"]}
    assert sgd["capture PSNR dB sRGB"] == pytest.approx(captured["sgd"], abs=1e-3)
    assert sgd["capture PSNR dB sRGB"] > dpac["capture PSNR dB sRGB"] + 1.0, front
    assert sgd["seconds per frame"] > dpac["seconds per frame"] and sgd["on front"] and dpac["on front"]
    report = (folder / "report.html").read_text()
    section = report[report.index("Speed against error across methods"):]
    assert section.count("<circle") == 2 and "log scale" in section and ">sgd<" in section


@pytest.mark.parametrize("value, problem", [("3", "expected a string or a list of strings"),
                                            ("[]", "at least 1 entry required")])
def test_colour_capture_method_must_name_methods(tmp_path: Path, bench_profile_path: Path, capture_procedure: Path,
                                                 value: str, problem: str) -> None:
    write(capture_procedure, CAPTURE + f"method = {value}\n")
    with pytest.raises(BenchctlError, match=f"parameters.method: {problem}"):
        run_procedure(capture_procedure, profile=str(bench_profile_path), out=tmp_path / "runs", say=lambda _: None)


def test_several_methods_give_the_checkpoint_to_the_learned_ones(tmp_path: Path, bench_profile_path: Path,
                                                                 capture_procedure: Path) -> None:
    settings = TrainSettings(method="ccnn", data="procedural:2", epochs=1, lr=1e-3, val_fraction=0.5)
    checkpoint = train(load_profile(bench_profile_path), settings, tmp_path / "ckpt", {"red": 0, "green": 1, "blue": 2},
                       out=lambda _: None).checkpoint
    write(capture_procedure, CAPTURE + 'method = ["dpac", "ccnn", "sgd"]\niterations = 5\n'
          + f'checkpoint = "{checkpoint}"\n')
    lines: list[str] = []
    outcome = run_procedure(capture_procedure, profile=str(bench_profile_path), out=tmp_path / "runs", dry_run=True,
                            say=lines.append)
    assert outcome.folder is None and any("hologram/bars-ccnn/green" in line for line in lines)
    write(capture_procedure, CAPTURE + f'method = ["dpac", "sgd"]\ncheckpoint = "{checkpoint}"\n')
    with pytest.raises(BenchctlError, match=r"parameters.checkpoint: none of the methods \['dpac', 'sgd'\] is a "
                                            "learned method that takes one"):
        run_procedure(capture_procedure, profile=str(bench_profile_path), out=tmp_path / "runs", dry_run=True,
                      say=lambda _: None)
    write(capture_procedure, CAPTURE + 'method = ["dpac", "nope"]\n')
    with pytest.raises(BenchctlError, match="parameters.method: unknown hologram method 'nope'"):
        run_procedure(capture_procedure, profile=str(bench_profile_path), out=tmp_path / "runs", dry_run=True,
                      say=lambda _: None)


def test_front_plot_labels_stay_inside_the_frame() -> None:
    def labels(svg: str) -> dict[str, tuple[float, str | None]]:
        found = re.finditer(r'<text x="([\d.]+)" y="[\d.]+" fill="#\w+"( text-anchor="end")?>([\w-]+)</text>', svg)
        return {m.group(3): (float(m.group(1)), m.group(2)) for m in found}

    two = labels(front_plot([("dpac", 2.85, 28.3, True), ("ccnn-dcm4", 3.87, 30.3, True)], "seconds", "PSNR"))
    assert two["dpac"][1] is None  # left half: the label starts right of its marker
    assert two["ccnn-dcm4"][1] and two["ccnn-dcm4"][0] < 560 - 8  # right edge: it ends left of its marker
    svg = front_plot([("dpac", 2.85, 28.3, True), ("ccnn-dcm4", 3.87, 30.3, True), ("slow", 40.0, 20.0, False)],
                     "seconds", "PSNR")
    three = labels(svg)
    assert three["ccnn-dcm4"][1] is None and three["slow"][1]  # now left of centre / at the right edge
    assert svg.count('fill="white"') == 1  # off the front: a hollow marker
