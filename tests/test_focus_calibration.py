"""Focus calibration: the sharpness, peak and map arithmetic, then the procedure on a small simulated bench against the
simulator's hidden mechanics (backlash, where each depth truly is), its acceptance test, and `benchctl focus go`."""

from __future__ import annotations

import itertools
import json
import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from benchctl.calibration.store import Calibration
from benchctl.capture.focus import FLOOR, FocusMap, fit_peak, parse_depth, sharpness
from benchctl.cli import main
from benchctl.devices.sim import physics
from benchctl.devices.sim.focus_mechanics import Mechanism
from benchctl.errors import BadValueError, BenchctlError
from benchctl.profiles import Profile
from benchctl.runner.focus_commands import focus_go

BACKLASH = 25.0
PEAK_UM = 50  # a tenth of the depth of field (lambda / NA^2 = 0.49 mm)
SWEEP = """name = "focus-calibration"
procedure = "focus-calibration"
[parameters]
colours = ["green"]
sweep_steps = [0, 4000]
fine_span_steps = 300
round_trip_steps = 500
dot_radius_px = 1.0
iterations = 20
coarse_points = 11
fine_points = 7
"""


@pytest.mark.parametrize("text, metres", [("70mm", 0.07), ("70.5 mm", 0.0705), ("0.07m", 0.07), ("14.3D", 1 / 14.3),
                                          ("20 dpt", 0.05)])
def test_depths_in_millimetres_or_diopters(text: str, metres: float) -> None:
    assert parse_depth(text) == pytest.approx(metres)


@pytest.mark.parametrize("text", ["70", "seven mm", "-3mm", "0D"])
def test_bad_depths_are_one_line_errors(text: str) -> None:
    with pytest.raises(BadValueError, match="depth"):
        parse_depth(text)


def test_sharpness_is_exposure_free_and_falls_as_a_point_spreads() -> None:
    image = np.zeros((64, 64))
    image[28:32, 28:32] = 1.0
    wide = np.zeros((64, 64))
    wide[24:40, 24:40] = 1 / 16
    assert sharpness(image) == pytest.approx(sharpness(7 * image)) == pytest.approx(256.0)  # one bin of 256
    assert sharpness(wide) == pytest.approx(16.0)  # spread over 16 bins


def test_sharpness_stays_exposure_free_where_faint_light_meets_the_noise() -> None:
    # dots holding a third of the light over a faint even glow (a phase-only dot hologram's), with read noise: at an
    # eighth of the exposure the glow sinks into the noise, and what is counted must not change with it
    rng = np.random.default_rng(1)
    scene = np.full((512, 512), 2e-4)
    for y, x in itertools.product(range(40, 512, 96), repeat=2):
        scene[y:y + 8, x:x + 8] = 0.05
    values = [sharpness(scale * scene + rng.normal(0, 3e-4, scene.shape), FLOOR) for scale in (8.0, 2.0, 1.0)]
    assert values == pytest.approx([values[0]] * 3, rel=0.02)
    assert values[0] == pytest.approx(sharpness(scene, FLOOR), rel=0.02)
    unfloored = [sharpness(scale * scene + rng.normal(0, 3e-4, scene.shape)) for scale in (8.0, 1.0)]
    assert unfloored[1] < 0.9 * unfloored[0]


def test_fit_peak_finds_a_gaussian_vertex_between_samples_and_refuses_an_edge() -> None:
    x = np.arange(0, 1100, 100.0)
    assert fit_peak(x, 5 + np.exp(-((x - 437.0) / 300) ** 2)) == pytest.approx(437.0, abs=15)
    assert fit_peak(x, np.exp(-((x - 437.0) / 300) ** 2)) == pytest.approx(437.0, abs=1e-6)
    with pytest.raises(BenchctlError, match="outside the swept range"):
        fit_peak(x, np.exp(-((x - 1500.0) / 300) ** 2))


def test_focus_map_fits_inverts_and_round_trips_through_json() -> None:
    points = [(1000.0, 19.0), (2000.0, 20.0), (3000.0, 21.0)]
    found = FocusMap.fit(points, approach=1, backlash_steps=25.0, repeatability_steps=1.5, range_steps=(0.0, 4000.0))
    assert found.residual_mm == pytest.approx(0.0, abs=1e-9) and found.depth_mm(2500) == pytest.approx(20.5)
    assert found.steps_for(0.0205) == 2500 and found.overshoot_steps == 50
    assert FocusMap.from_dict(json.loads(json.dumps(found.to_dict()))) == found
    with pytest.raises(BenchctlError, match="outside what the focus calibration covers"):
        found.steps_for(0.030)
    with pytest.raises(BenchctlError, match="three depths"):
        FocusMap.fit(points[:2], approach=1, backlash_steps=0, repeatability_steps=None, range_steps=(0, 1))


def stage_bench(make_bench_profile: Callable[..., Profile], efficiency: float = 1e-5) -> Profile:
    """The small simulated bench (20 mm, 8 um, no iris: depth of field about 0.5 mm at 520 nm) with its camera on a
    simulated stage: 1 um per step, 4 mm of travel, focused on the target plane at power-on, 25 steps of backlash;
    `efficiency`: the fraction of the laser's light reaching the sensor."""
    return make_bench_profile(
        optics={"iris_fraction": None},
        focus={"driver": "zaber", "port": "sim://focus-stage?dialect=zaber", "settle_ms": 0},
        sim={"focus": {"mm_per_step": 0.001, "range_steps": 4000, "start_steps": 2000, "backlash_steps": BACKLASH},
             "beam": {"efficiency": efficiency}})


@pytest.fixture
def focus_bench(make_bench_profile: Callable[..., Profile]) -> Profile:
    return stage_bench(make_bench_profile)


def run_calibration(tmp_path: Path, profile: Profile, extra: str = "") -> tuple[int, Path]:
    procedure = tmp_path / "focus.toml"
    procedure.write_text(SWEEP + extra)
    runs = tmp_path / "runs"
    code = main(["run", str(procedure), "--profile", str(profile.path), "--out", str(runs)])
    return code, sorted(runs.iterdir())[-1]


def results(run: Path) -> dict[str, dict]:
    return {line["step"]: line["result"] for line in map(json.loads, (run / "steps.jsonl").read_text().splitlines())
            if line.get("result") is not None and "step" in line}


@pytest.mark.slow
def test_calibration_recovers_the_mechanics_and_focus_go_lands_on_the_depth(
        tmp_path: Path, make_bench_profile: Callable[..., Profile], capsys: pytest.CaptureFixture[str]) -> None:
    # ten times brighter than the other tests: its focused dots would clip the sensor a hundredfold at the
    # setpoint, flattening the very peak the sweep looks for; each such frame is retaken lower (sharpness is
    # exposure-free)
    focus_bench = stage_bench(make_bench_profile, efficiency=1e-4)
    code, run = run_calibration(tmp_path, focus_bench, 'setpoints = { green = "100%" }\n')
    assert code == 0
    steps = results(run)
    coarse = steps["focus/green/coarse"]
    assert min(min(powers) for powers in coarse["power_w"]) < 0.03 * focus_bench.channel("green").max_power_mw * 1e-3
    fit = steps["focus/green/fit"]
    assert fit["calibration"]["stored"] and fit["simulator"]["backlash_steps"] == BACKLASH
    assert fit["map"]["backlash_steps"] == pytest.approx(BACKLASH, abs=6)
    # each depth's up-sweep peak is where the counter stands when the carriage (counter - backlash) focuses there
    for depth, peak in zip((19.0, 20.0, 21.0), (p["steps"] for p in fit["map"]["points"])):
        assert peak - BACKLASH == pytest.approx(2000 + (depth - 20.0) * 1000, abs=PEAK_UM)
    repeat = steps["focus/green/repeat"]
    assert len(repeat["read_steps"]) == 20 and repeat["true_repeatability_steps"] == 0.0
    assert repeat["repeatability_steps"] < 5  # a stage without step spread comes back: what is left is noise
    stored = Calibration.store(focus_bench).focus_maps()["green"]
    assert stored["run"] == run.name and stored["focus"] == "zaber sim://focus-stage?dialect=zaber"
    assert "Focus calibration" in (run / "report.html").read_text()

    lines = focus_go(focus_bench, "20.5mm", None)
    assert "green: 20.5 mm from the SLM" in lines[0]
    assert physics.camera_focus_m(focus_bench) == pytest.approx(0.0205, abs=PEAK_UM * 1e-6)  # the camera's true plane
    assert main(["focus", "go", "19.2mm", "--profile", str(focus_bench.path)]) == 0
    assert physics.camera_focus_m(focus_bench) == pytest.approx(0.0192, abs=PEAK_UM * 1e-6)  # arrived from below
    assert main(["focus", "status", "--profile", str(focus_bench.path)]) == 0
    assert "green: focused at 19.2 mm from the SLM (calibrated)" in capsys.readouterr().out


@pytest.mark.slow
def test_a_map_that_fails_its_acceptance_test_is_kept_aside_and_the_run_fails(tmp_path: Path,
                                                                               focus_bench: Profile) -> None:
    code, run = run_calibration(tmp_path, focus_bench, "max_residual_mm = 1e-9\nround_trips = 2\n")
    assert code == 2
    fit = results(run)["focus/green/fit"]
    assert not fit["calibration"]["stored"] and "above the bound" in fit["calibration"]["failures"][0]
    assert Calibration.store(focus_bench).focus_maps() == {}
    assert any(Path(kept).name.endswith("focus-green.json") and Path(kept).is_file()
               for kept in fit["calibration"]["kept"])
    with pytest.raises(BenchctlError, match="no focus calibration"):
        focus_go(focus_bench, "20mm", None)


@pytest.mark.slow
def test_round_trips_near_the_end_of_the_travel_go_below(tmp_path: Path, focus_bench: Profile) -> None:
    """The middle depth 1.2 mm beyond the target plane (3225 steps on a 4000-step travel): round trips of 1000 steps
    above it would pass the end stop (the stage refuses such a move and the run stopped there), so they go below it and
    come back from there."""
    procedure = tmp_path / "focus.toml"
    procedure.write_text(SWEEP.replace("round_trip_steps = 500", "round_trip_steps = 1000")
                         + "depths_mm = [1.2, 1.5, 1.8]\nround_trips = 2\n")
    runs = tmp_path / "runs"
    assert main(["run", str(procedure), "--profile", str(focus_bench.path), "--out", str(runs)]) == 0
    steps = results(sorted(runs.iterdir())[-1])
    repeat = steps["focus/green/repeat"]
    assert 2200 < repeat["position"] < 3225 and len(repeat["read_steps"]) == 2
    fit = steps["focus/green/fit"]
    assert fit["calibration"]["stored"]
    for depth, peak in zip((21.2, 21.5), (p["steps"] for p in fit["map"]["points"])):  # (21.8's sweep is cut at 4000)
        assert peak - BACKLASH == pytest.approx(2000 + (depth - 20.0) * 1000, abs=PEAK_UM)


def test_focus_go_uses_the_stored_map_from_its_side(focus_bench: Profile) -> None:
    found = FocusMap.fit([(1000.0, 19.0), (2000.0, 20.0), (3000.0, 21.0)], approach=1, backlash_steps=BACKLASH,
                         repeatability_steps=1.0, range_steps=(0.0, 4000.0))
    Calibration.store(focus_bench).save_focus("green", {**found.to_dict(), "unit": "microstep"})
    focus_go(focus_bench, "20.25mm", "green")  # homes first, then up from below: 2250 counted
    assert Mechanism(focus_bench.sim.focus).true_steps == 2250 - BACKLASH
    focus_go(focus_bench, "20mm", "green")  # coming down: past it by 2 x backlash, then up
    assert Mechanism(focus_bench.sim.focus).true_steps == 2000 - BACKLASH
    with pytest.raises(BenchctlError, match="'red' is not focus-calibrated"):
        focus_go(focus_bench, "20mm", "red")
    assert math.isclose(1 / parse_depth("50D"), 50)


def test_the_dry_run_counts_every_sweep_capture(tmp_path: Path, focus_bench: Profile,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    procedure = tmp_path / "focus.toml"
    procedure.write_text(SWEEP)
    assert main(["run", str(procedure), "--profile", str(focus_bench.path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    captures = 11 * 3 + 3 * 2 * 7 + 20  # coarse x depths, up and down per depth, round trips
    assert f"({captures} frame(s) at about" in out and "11 x green alone at 2 mW" not in out
    assert "33 x green alone at 2 mW, 1 frame(s) + 0 dark, RAW not kept" in out
    assert "disk: about 0 kB in runs (0 RAW frame(s)" in out


@pytest.mark.parametrize("extra, message", [
    ("depths_mm = [-30.0, 0.0, 1.0]\n", "parameters.depths_mm: -30 mm puts a depth behind the SLM"),
    ("depths_mm = [0.0, 1.0]\n", "depths_mm"),
    ("sweep_steps = [500, 100]\n", "parameters.sweep_steps: \\[500, 100\\] must be two positions"),
])
def test_bad_sweeps_are_refused_when_planning(tmp_path: Path, focus_bench: Profile, extra: str, message: str,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    procedure = tmp_path / "focus.toml"
    procedure.write_text(SWEEP.replace("sweep_steps = [0, 4000]\n", "") + extra)
    assert main(["run", str(procedure), "--profile", str(focus_bench.path), "--dry-run"]) == 2
    assert re.search(message, capsys.readouterr().err)
