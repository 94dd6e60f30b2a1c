"""Focal-stack capture (procedures/focal_stack.toml) on a small simulated bench whose camera rides on a simulated
Zaber stage: every plane is focused through the stored focus map from its calibrated side, each plane's in-focus
region is sharpest in the capture focused there, the dry run lists the focus moves and their time, a run resumes
without capturing twice and focuses again, bad input is one line, and the report steps through depth in a real
browser."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import test_console_browser
import torch
from conftest import SMALL_BENCH, one_error_line, truly_focused, truly_registered
from selenium import webdriver
from selenium.webdriver.common.by import By

from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.store import Calibration
from benchctl.capture.colour_planes import captured_amplitude, merge_colours, registered_plane
from benchctl.capture.focus import FocusMap
from benchctl.capture.raw import decode_raw, subtract_dark
from benchctl.cli import main
from benchctl.devices.errors import DeviceError
from benchctl.devices.sim.focus_mechanics import Mechanism
from benchctl.devices.sim.state import load_state
from benchctl.holograms.cache import hologram
from benchctl.optics.focal_stack import FocalStackTarget, masked_colour_scores, masked_scores
from benchctl.optics.metrics import centred_slices
from benchctl.optics.planes import PlaneChoice
from benchctl.profiles import Profile
from benchctl.runner.engine import run_procedure
from benchctl.scenes import load_scene, prepare_scene

browser = test_console_browser.browser  # the console tests' headless Chromium (a fixture)
BACKLASH = 25.0
PLANES_MM = (17.0, 20.0, 23.0)  # rgbd:three-planes across the depth range: 0, 50 and 100 %
STACK = """procedure = "focal-stack"
[parameters]
colours = ["green"]
iterations = 20
frames = 1
dark_frames = 1
"""


@pytest.fixture
def stack_bench(make_bench_profile: Callable[..., Profile]) -> Profile:
    """The tests' small bench (64 x 96 SLM, 8 um, 20 mm, iris 0.5: axial resolution 1.84-2.27 mm) showing depths
    17 .. 23 mm, its camera on a simulated stage (1 um per step, 25 steps of backlash, at 20 mm at power-on)."""
    return make_bench_profile(
        SMALL_BENCH, optics={"depth_range_mm": [17.0, 23.0]},
        focus={"driver": "zaber", "port": "sim://focus-stage?dialect=zaber", "settle_ms": 0},
        sim={"focus": {"mm_per_step": 0.001, "range_steps": 8000, "start_steps": 4000, "backlash_steps": BACKLASH}})


@pytest.fixture
def ready_bench(stack_bench: Profile) -> Profile:
    """The stack bench registered and focus-calibrated (the simulator's true homography and focus map)."""
    return truly_focused(truly_registered(stack_bench, "red", "green", "blue"), "red", "green", "blue")


def write(tmp_path: Path, text: str, name: str = "stack.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def results(run: Path) -> dict[str, dict]:
    return {line["step"]: line["result"] for line in map(json.loads, (run / "steps.jsonl").read_text().splitlines())
            if line.get("result") is not None and "step" in line}


def shutter_count() -> int:
    return int(load_state("sim-camera").get("frame", 0))


def in_focus_psnr(profile: Profile, run: Path) -> np.ndarray:
    """[j, k]: green amplitude PSNR of plane k's in-focus region in the capture focused at plane j, from the RAW frames
    registered through the simulator's true homography (not the procedure's own processing)."""
    slm, optics = profile.section("slm"), profile.section("optics")
    amplitude, depth = prepare_scene(load_scene("rgbd:three-planes", optics.roi, optics.depth_range_m), slm.shape,
                                     optics.roi)
    rows, cols = centred_slices(slm.shape, optics.roi)
    owner = FocalStackTarget(amplitude[1], depth, tuple(z * 1e-3 for z in PLANES_MM)).masks[:, rows, cols].argmax(0)
    homography = np.asarray(Calibration.store(profile).registrations()["green"]["homography"])
    table = np.zeros((3, 3))
    for j in range(3):
        raw = run / "raw" / "capture" / "three-planes" / f"plane-{j + 1}" / "green"
        image = subtract_dark(decode_raw(raw / "frame-000.dng"), decode_raw(raw / "dark-000.dng"))
        signal = registered_plane(image, 1, homography, slm.shape, optics.roi)
        for k in range(3):
            table[j, k] = masked_scores(captured_amplitude(signal), amplitude[1, rows, cols], owner == k)[
                "psnr_amplitude_db"]
    return table


@pytest.mark.slow
def test_each_plane_is_focused_from_its_side_and_scored_where_it_is_in_focus(tmp_path: Path,
                                                                             ready_bench: Profile) -> None:
    outcome = run_procedure(write(tmp_path, STACK), profile=str(ready_bench.path), out=tmp_path / "runs",
                            say=lambda line: None)
    run = outcome.folder
    assert run is not None
    steps = results(run)
    found = FocusMap.from_dict(Calibration.store(ready_bench).focus_maps()["green"])
    for k, depth in enumerate(PLANES_MM):
        moved = steps[f"capture/three-planes/plane-{k + 1}/green"]["focus"]
        assert moved["depth_mm"] == pytest.approx(depth) and moved["steps"] == found.steps_for(depth * 1e-3)
        assert moved["position"] == moved["reported"] == moved["steps"] == round(4000 + BACKLASH + (depth - 20) * 1000)
        assert steps[f"probe/three-planes/green/plane-{k + 1}"]["focus"]["steps"] == moved["steps"]
    # the last plane was approached from below, past the backlash: the carriage truly focuses at 23 mm
    assert Mechanism(distance_mm=20.0).plane_m == pytest.approx(0.023, abs=1e-9)
    # each plane's in-focus region is sharpest in the capture focused at it, by a margin
    table = in_focus_psnr(ready_bench, run)
    for k in range(3):
        others = [table[j, k] for j in range(3) if j != k]
        assert table[k, k] > max(others) + 0.5, table
    metrics = json.loads((run / "metrics.json").read_text())
    (scene,) = metrics["scenes"]
    assert [p["depth_mm"] for p in scene["planes"]] == pytest.approx(PLANES_MM)
    assert "3 plane(s) at 17.00, 20.00, 23.00 mm" in scene["planes_reason"]
    captured = [p["capture"]["psnr_amplitude_db"] for p in scene["planes"]]
    assert captured == pytest.approx(np.diag(table), abs=0.01)  # the procedure scores what the frames hold
    assert scene["mean"]["capture"]["psnr_amplitude_db"] == pytest.approx(np.mean(captured), abs=1e-3)
    simulated = [p["simulated"]["psnr_amplitude_db"] for p in scene["planes"]]
    assert scene["mean"]["simulated"]["psnr_amplitude_db"] == pytest.approx(np.mean(simulated), abs=1e-3)
    assert all(10 < c < s for c, s in zip(captured, simulated))  # the bench's own losses, never above the model
    # one power for every plane: the lowest the three probes chose
    chosen = [steps[f"probe/three-planes/green/plane-{k}"]["auto_exposure"]["power_w"] for k in (1, 2, 3)]
    assert [steps[f"capture/three-planes/plane-{k}/green"]["setpoint_w"] for k in (1, 2, 3)] == \
        pytest.approx([min(chosen)] * 3, rel=5e-3)  # read back at the laser's 0.01 mW
    assert outcome.headline[0].startswith(f"three-planes: mean in-focus PSNR {np.mean(captured):.2f} dB captured")
    rows = (run / "metrics.csv").read_text().splitlines()
    assert len(rows) == 1 + 3 + 1 and rows[-1].startswith("rgbd:three-planes,mean,")


@pytest.mark.slow
def test_colour_capture_takes_a_scene_with_depth_as_a_focal_stack(tmp_path: Path, ready_bench: Profile) -> None:
    procedure = write(tmp_path, 'procedure = "colour-capture"\n[parameters]\ncolours = ["green"]\nframes = 1\n'
                                'targets = ["chart:bars", "rgbd:two-planes"]\nlut_calibration = "skip"\n')
    outcome = run_procedure(procedure, profile=str(ready_bench.path), out=tmp_path / "runs", say=lambda line: None)
    assert outcome.folder is not None
    assert outcome.headline[0].startswith("bars: merged capture PSNR")
    assert outcome.headline[1].startswith("two-planes: mean in-focus PSNR") and "dpac" in outcome.headline[1]
    steps = results(outcome.folder)
    assert [steps[f"capture/two-planes/plane-{k}/green"]["focus"]["depth_mm"] for k in (1, 2)] == \
        pytest.approx([17.6, 22.4])  # the scene's layers at 10 and 90 % of the depth range
    assert steps["capture/bars/green"]["focus"]["depth_mm"] == pytest.approx(20.0)  # a 2D target: the target plane
    metrics = json.loads((outcome.folder / "metrics.json").read_text())
    assert [t["label"] for t in metrics["targets"]] == ["bars"] and metrics["scenes"][0]["label"] == "two-planes"
    page = (outcome.folder / "report.html").read_text()
    assert "Scene rgbd:two-planes (two-planes)" in page and "plane 2 of 2: 22.40 mm" in page


def test_the_dry_run_lists_every_focus_move_and_its_time(tmp_path: Path, ready_bench: Profile,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", str(write(tmp_path, STACK)), "--profile", str(ready_bench.path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    for k, steps in enumerate((1025, 4025, 7025)):
        line = next(line for line in out.splitlines() if f"capture/three-planes/plane-{k + 1}/green:" in line)
        assert f"[focus green at {PLANES_MM[k]:.2f} mm: {steps} steps from home, from below]" in line
    assert "6 focus move(s) at about 0.5 s each" in out  # three probes and three captures
    assert not load_state("sim-focus").get("moves")  # nothing moved
    capped = write(tmp_path, STACK + 'max_exposure_power = "3mW"\n', "capped.toml")
    assert main(["run", str(capped), "--profile", str(ready_bench.path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    line = next(line for line in out.splitlines() if "capture/three-planes/plane-2/green:" in line)
    assert "[green alone at a power chosen when the step runs (at most 3 mW), 1 frame(s) + 1 dark]" in line
    assert "  green: 6 exposure(s), at most 3 mW (3 at a power chosen at run time, up to 3 mW); limit 40 mW" in out


def test_a_capture_at_the_target_plane_focuses_there_once_the_focus_is_calibrated(
        tmp_path: Path, stack_bench: Profile, capsys: pytest.CaptureFixture[str]) -> None:
    capture = write(tmp_path, 'procedure = "colour-capture"\n[parameters]\ncolours = ["green"]\n'
                              'lut_calibration = "skip"\nregistration = "stored"\n')
    dots = write(tmp_path, 'procedure = "registration"\n[parameters]\ncolours = ["green"]\ngrid = [6, 8]\n',
                 "dots.toml")
    truly_registered(stack_bench)
    for procedure in (capture, dots):
        assert main(["run", str(procedure), "--profile", str(stack_bench.path), "--dry-run"]) == 0
        assert "focus green" not in capsys.readouterr().out  # not calibrated: the focus is left where it is
    truly_focused(stack_bench)
    for procedure, key in ((capture, "probe/bars/green:"), (capture, "capture/bars/green:"),
                           (dots, "registration/capture/green:")):
        assert main(["run", str(procedure), "--profile", str(stack_bench.path), "--dry-run"]) == 0
        line = next(x for x in capsys.readouterr().out.splitlines() if key in x)
        assert "[focus green at 20.00 mm: 4025 steps from home, from below]" in line


@pytest.mark.parametrize("text, message", [
    ('scenes = ["chart:bars"]', "parameters.scenes: 'chart:bars' is not a scene with depth"),
    ('scenes = ["rgbd:four-planes"]', "parameters.scenes: rgbd:four-planes: no bundled scene"),
    ('method = "gs"', "parameters.method: 'gs' makes holograms of one plane; rgbd:three-planes is shown on 3 planes "
                      "and needs one of: dpac, sgd"),
    ("planes = 17", "parameters.planes: must be <= 16, got 17"),
])
def test_bad_parameters_are_one_line(tmp_path: Path, ready_bench: Profile, capsys: pytest.CaptureFixture[str],
                                     text: str, message: str) -> None:
    line = one_error_line(capsys, ["run", str(write(tmp_path, STACK + text + "\n")), "--profile",
                                   str(ready_bench.path), "--dry-run"])
    assert message in line


def test_without_a_focus_calibration_the_plan_says_to_calibrate(tmp_path: Path, stack_bench: Profile,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    line = one_error_line(capsys, ["run", str(write(tmp_path, STACK)), "--profile", str(stack_bench.path),
                                   "--dry-run"])
    assert "no focus calibration for green on profile 'bench'" in line and "focus_calibration.toml first" in line


def test_a_step_cannot_move_the_focus_it_did_not_declare(tmp_path: Path, ready_bench: Profile) -> None:
    code = write(tmp_path, '''from benchctl.runner.api import Context, FocusAt, Parameters, Step

DESCRIPTION = "moves the focus without saying so"
PARAMETERS = Parameters


def plan(context: Context) -> list[Step]:
    declared = FocusAt("green", 0.02, 4025, 1, 50)
    return [Step("move", "a declared move, then another", _move, focus=(declared,))]


def _move(context: Context) -> dict:
    context.focus_at(FocusAt("green", 0.02, 4025, 1, 50))
    context.focus_at(FocusAt("green", 0.021, 5025, 1, 50))
    return {}
''', "mover.py")
    with pytest.raises(Exception, match=r"moves the focus \(focus green at 21.00 mm: 5025 steps from home, from "
                                        r"below\), which it did not declare"):
        run_procedure(code, profile=str(ready_bench.path), out=tmp_path / "runs", say=lambda line: None)
    assert Mechanism().true_steps == 4000  # the declared move went to 4025 counted, 4000 true; the other never ran


@pytest.mark.slow
def test_a_resumed_stack_focuses_again_and_captures_nothing_twice(tmp_path: Path, ready_bench: Profile) -> None:
    procedure = write(tmp_path, STACK)
    # probes take frames 1-3, plane 1 frames 4-5 (frame + dark): the cable is pulled before plane 2's dark frame
    assert main(["sim", "fault", "sim-camera", "unplug_at=7"]) == 0
    with pytest.raises(DeviceError, match="cable pulled before frame 7"):
        run_procedure(procedure, profile=str(ready_bench.path), out=tmp_path / "runs", say=lambda line: None)
    (run,) = (tmp_path / "runs").iterdir()
    assert shutter_count() == 6
    assert main(["sim", "fault", "sim-camera", "--clear"]) == 0
    assert main(["focus", "move", "-1500", "--profile", str(ready_bench.path)]) == 0  # someone moved it meanwhile
    outcome = run_procedure(None, resume=run, say=lambda line: None)
    assert outcome.ran[0] == "capture/three-planes/plane-2/green"
    assert "capture/three-planes/plane-1/green" in outcome.skipped
    assert shutter_count() == 3 + 3 * 2 + 1  # every frame once, and the one captured before the cable was pulled
    moved = results(run)["capture/three-planes/plane-2/green"]["focus"]
    assert moved["position"] == 4025 and moved["requested"] == 1500  # from 2525, where it was moved to
    table = in_focus_psnr(ready_bench, run)
    assert table[1, 1] > max(table[0, 1], table[2, 1])


def test_a_focal_stack_hologram_is_cached_by_its_depth_and_planes(ready_bench: Profile) -> None:
    bench = Calibrated.stored(ready_bench)
    slm, optics = ready_bench.section("slm"), ready_bench.section("optics")
    amplitude, depth = prepare_scene(load_scene("rgbd:three-planes", optics.roi, optics.depth_range_m), slm.shape,
                                     optics.roi)
    planes = tuple(z * 1e-3 for z in PLANES_MM)

    def make(depth_m: torch.Tensor, planes_m: tuple[float, ...]):
        return hologram(bench, amplitude, "green", "dpac", iterations=None, seed=0, checkpoint=None, depth_m=depth_m,
                        planes=PlaneChoice(planes_m, "as given"))

    first = make(depth, planes)
    assert not first.cached and first.reconstruction.shape == (3, *optics.roi) and len(first.plane_scores) == 3
    again = make(depth, planes)
    assert again.cached and np.array_equal(again.gray, first.gray) and again.plane_scores == first.plane_scores
    assert not make(depth, planes[:2]).cached
    assert not make(depth.flip(-1).contiguous(), planes).cached


def test_colours_are_balanced_over_the_in_focus_region_and_scored_there() -> None:
    target = torch.full((3, 4, 6), 0.5)
    region = torch.zeros(4, 6, dtype=torch.bool)
    region[:, :3] = True
    captured = torch.full((4, 6), 0.25)
    captured[:, 3:] = 1.0  # out of focus: another brightness, which must not set the gain
    merged = merge_colours({1: captured}, target, region)
    assert merged.gains[1] == pytest.approx(2.0)
    assert torch.allclose(merged.linear[1, :, :3], torch.full((4, 3), 0.25))
    scores = masked_colour_scores(merged.linear, target * torch.tensor([0.0, 1.0, 0.0])[:, None, None], region)
    assert scores is not None and scores["psnr_linear_db"] == pytest.approx(100.0)  # identical: the cap
    worse = masked_colour_scores(merged.linear * 0.5, target * torch.tensor([0.0, 1.0, 0.0])[:, None, None], region)
    # 0.125 off on one colour of three: mse = 0.125^2 / 3
    assert worse is not None and worse["psnr_linear_db"] == pytest.approx(10 * np.log10(3 / 0.125**2), abs=1e-4)
    assert masked_colour_scores(merged.linear, target, torch.zeros(4, 6, dtype=torch.bool)) is None


@pytest.mark.slow
@pytest.mark.parametrize("width", [1400, 1000])
def test_the_report_steps_through_depth(tmp_path: Path, ready_bench: Profile, browser: webdriver.Chrome,
                                        width: int) -> None:
    outcome = run_procedure(write(tmp_path, STACK), profile=str(ready_bench.path), out=tmp_path / "runs",
                            say=lambda line: None)
    assert outcome.folder is not None
    browser.set_window_size(width, 1000)
    browser.get((outcome.folder / "report.html").as_uri())
    page = browser.execute_script("const e = document.documentElement; return [e.scrollWidth, e.clientWidth];")
    assert page[0] <= page[1], f"the page scrolls sideways at {width} px: {page}"
    frames = browser.find_elements(By.CSS_SELECTOR, ".frames .frame")
    assert [f.find_element(By.TAG_NAME, "h4").text for f in frames] == [
        f"plane {k} of 3: {z:.2f} mm" for k, z in zip((1, 2, 3), PLANES_MM)]
    for frame, depth in zip(frames, PLANES_MM):  # one row per plane: target in focus, simulated, captured
        captions = [c.text for c in frame.find_elements(By.TAG_NAME, "figcaption")]
        assert captions == [f"target, in focus at {depth:.2f} mm (the rest dimmed)", f"simulated at {depth:.2f} mm",
                            f"captured at {depth:.2f} mm"]
    slider = browser.find_element(By.CSS_SELECTOR, ".stepper input[type=range]")
    output = browser.find_element(By.CSS_SELECTOR, ".stepper output")
    view = browser.find_element(By.CSS_SELECTOR, ".stepper .view")
    for k in (0, 2, 1):
        browser.execute_script("arguments[0].value = arguments[1]; arguments[0].dispatchEvent(new Event('input'));",
                               slider, k)
        assert output.text == f"plane {k + 1} of 3: {PLANES_MM[k]:.2f} mm"
        shown = [img.get_attribute("src") for img in view.find_elements(By.TAG_NAME, "img")]
        assert shown == [img.get_attribute("src") for img in frames[k].find_elements(By.TAG_NAME, "img")]
        assert len(shown) == 3 and all(s.startswith("data:image/png;base64,") for s in shown)
    # the keyboard moves it too: the slider is a native range input
    slider.send_keys("\ue012")  # left arrow
    assert output.text == f"plane 1 of 3: {PLANES_MM[0]:.2f} mm"
    table = browser.find_element(By.CSS_SELECTOR, "table").text
    assert "mean" in table and "captured PSNR dB" in table and "green focus steps" in table


def test_a_scenes_hologram_sets_the_dry_runs_memory_and_a_sweep_beyond_the_limit_is_refused(
        tmp_path: Path, ready_bench: Profile, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    from benchctl.memory import INTERPRETER_BYTES, depth_estimate, size_text

    tilted = write(tmp_path, STACK + 'scenes = ["rgbd:tilted"]\n')
    monkeypatch.setenv("BENCHCTL_MAX_MEMORY", "1T")
    assert main(["run", str(tilted), "--profile", str(ready_bench.path), "--dry-run"]) == 0
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("memory: "))
    depths, planes = (int(n) for n in re.search(r"holding (\d+) depth\(s\) for (\d+) plane\(s\)", line).groups())
    assert depths > planes > 1  # swept
    swept = depth_estimate(ready_bench, depths, planes)
    assert line == (f"memory: about {size_text(swept.peak)} at the run's peak, a hologram holding {depths} depth(s) "
                    f"for {planes} plane(s); limit 1.1 TB of memory here")
    limit = int(INTERPRETER_BYTES + swept.fixed + 1.5 * (swept.per["depths"] + swept.per["planes"]))
    monkeypatch.setenv("BENCHCTL_MAX_MEMORY", str(limit))
    line = one_error_line(capsys, ["run", str(tilted), "--profile", str(ready_bench.path), "--dry-run"])
    assert line == (f"benchctl: error: {tilted}: parameters.scenes: rgbd:tilted: a hologram holding {depths} depth(s) "
                    f"for {planes} plane(s) needs about {size_text(swept.peak)}, above the {size_text(limit)} of "
                    "memory here: 1 fixed plane(s) fit (parameters.planes = 1, no sweep) ($BENCHCTL_MAX_MEMORY sets "
                    "the limit)")
    one = write(tmp_path, STACK + 'scenes = ["rgbd:tilted"]\nplanes = 1\n', "one.toml")
    assert main(["run", str(one), "--profile", str(ready_bench.path), "--dry-run"]) == 0
