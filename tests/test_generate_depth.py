"""`benchctl generate rgbd:...` end to end on a small simulated bench: the planes chosen and why, the focal stack
written and scored per plane, a flat scene exactly as 2D, and what is refused."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchctl.cli import main


@pytest.fixture
def depth_profile(small_profile_path: Path) -> Path:
    """The small bench (64 x 96, 8 um, 20 mm) able to show depths 16 .. 24 mm."""
    text = small_profile_path.read_text().replace("roi = [48, 80]", "roi = [48, 80]\ndepth_range_mm = [16, 24]")
    small_profile_path.write_text(text)
    return small_profile_path


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.slow
def test_generate_a_two_plane_scene_writes_its_focal_stack_and_prints_the_planes(capsys, tmp_path, depth_profile):
    out = tmp_path / "stack"
    code, stdout, _ = _run(capsys, "generate", "rgbd:two-planes", "-m", "sgd", "-n", "5", "--planes", "auto",
                           "--colours", "green,red", "-p", str(depth_profile), "-o", str(out))
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert [p["distance_mm"] for p in metrics["planes"]] == pytest.approx([16.8, 23.2])
    assert [p["in_focus"] for p in metrics["planes"]] == pytest.approx([0.5, 0.5])
    assert "2 plane(s) at 16.80, 23.20 mm" in metrics["planes_reason"] and metrics["planes_reason"] in stdout
    for plane in metrics["planes"]:
        assert set(plane["scores"]) >= {"psnr_amplitude_db", "ssim_amplitude", "flip"}
    assert metrics["mean"]["psnr_amplitude_db"] == pytest.approx(
        np.mean([p["scores"]["psnr_amplitude_db"] for p in metrics["planes"]]))
    assert set(metrics["colours"]) == {"red", "green"}
    for name in ("plane_01_16.80mm.png", "plane_02_23.20mm.png", "target.png"):
        assert cv2.imread(str(out / name)).shape == (48, 80, 3), name
    depth = cv2.imread(str(out / "depth.png"), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16 and set(np.unique(depth)) == {0, 65535}
    assert metrics["depth_png_mm"] == pytest.approx([16.8, 23.2])
    assert {"phase_green.png", "phase_red.png"} <= set(metrics["files"])
    assert "plane       mm  in focus" in stdout and "mean" in stdout and "time: green" in stdout and "red " in stdout


def test_a_flat_scene_is_generated_and_scored_exactly_as_2d(capsys, tmp_path, depth_profile):
    flat, plain = tmp_path / "flat", tmp_path / "plain"
    code, stdout, _ = _run(capsys, "generate", "rgbd:flat", "--colours", "green", "-p", str(depth_profile),
                           "-o", str(flat))
    assert code == 0 and "1 plane at 20.00 mm" in stdout
    assert _run(capsys, "generate", "chart:siemens", "--colours", "green", "-p", str(depth_profile),
                "-o", str(plain))[0] == 0
    assert (flat / "phase_green.png").read_bytes() == (plain / "phase_green.png").read_bytes()
    three_d = json.loads((flat / "metrics.json").read_text())
    two_d = json.loads((plain / "metrics.json").read_text())
    assert len(three_d["planes"]) == 1 and three_d["planes"][0]["distance_mm"] == pytest.approx(20.0)
    for key in ("psnr_amplitude_db", "ssim_amplitude"):
        assert three_d["mean"][key] == pytest.approx(two_d["colours"]["green"][key], abs=1e-3)


@pytest.mark.slow
def test_a_fixed_number_of_planes_spreads_them_over_the_scenes_depth(capsys, tmp_path, depth_profile):
    out = tmp_path / "three"
    code, stdout, _ = _run(capsys, "generate", "rgbd:tilted", "--planes", "3", "--colours", "green",
                           "-p", str(depth_profile), "-o", str(out))
    assert code == 0
    planes = json.loads((out / "metrics.json").read_text())["planes"]
    assert [p["distance_mm"] for p in planes] == pytest.approx([16.0, 20.0, 24.0])
    assert "as asked" in stdout


@pytest.mark.slow
def test_auto_sweeps_a_tilted_scenes_planes_and_scores_it_all_in_focus(capsys, tmp_path, depth_profile):
    swept, layers = tmp_path / "swept", tmp_path / "layers"
    code, stdout, _ = _run(capsys, "generate", "rgbd:tilted", "-m", "sgd", "-n", "20", "--colours", "green",
                           "-p", str(depth_profile), "-o", str(swept))
    assert code == 0
    metrics = json.loads((swept / "metrics.json").read_text())
    assert len(metrics["planes"]) == 6 and len(metrics["sweep_mm"]) == 6
    for plane, depths in zip(metrics["planes"], metrics["sweep_mm"]):
        assert depths[0] < plane["distance_mm"] < depths[-1] and depths == sorted(depths)
    assert "each swept over its cluster" in stdout
    seen = metrics["mean"]["all_in_focus_psnr_db"]
    assert seen == pytest.approx(metrics["colours"]["green"]["mean"]["all_in_focus_psnr_db"])
    assert f"all in focus: PSNR {seen:.2f} dB (each pixel seen at the depth nearest its own of the sweep's)" in stdout
    assert _run(capsys, "generate", "rgbd:two-planes", "-m", "sgd", "-n", "5", "--colours", "green",
                "-p", str(depth_profile), "-o", str(layers))[0] == 0
    metrics = json.loads((layers / "metrics.json").read_text())
    assert metrics["sweep_mm"] is None and 10 < metrics["mean"]["all_in_focus_psnr_db"] < 60


def _tilted_green(depth_profile: Path):
    """The small bench, its green setup, the tilted scene on its SLM grid (amplitude, depth) and its green plane
    choice (auto)."""
    from benchctl.calibration.calibrated import Calibrated
    from benchctl.holograms.depth import scene_planes
    from benchctl.profiles import load_profile
    from benchctl.scenes import load_scene, prepare_scene

    profile = load_profile(depth_profile)
    optics, grid = profile.section("optics"), profile.section("slm").shape
    amplitude, depth = prepare_scene(load_scene("rgbd:tilted", optics.roi, optics.depth_range_m), grid, optics.roi)
    setup = Calibrated(profile).setup("green")
    rows, cols = setup.roi_slices
    return profile, setup, amplitude, depth, scene_planes(depth[rows, cols], amplitude[1, rows, cols] ** 2,
                                                          {"green": setup}, None)


def test_the_swept_all_in_focus_image_is_the_whole_stacks_a_few_depths_at_a_time(depth_profile, monkeypatch):
    import torch

    import benchctl.holograms.depth as depth_module
    from benchctl.holograms.depth import focal_stack_roi, swept_image
    from benchctl.optics.focal_stack import nearest_plane

    _, setup, _, depth, choice = _tilted_green(depth_profile)
    rows, cols = setup.roi_slices
    sweep = choice.sweep
    assert sweep is not None and len(sweep.all_m) > 7
    phase = torch.rand(setup.shape, generator=torch.Generator().manual_seed(3)) * 6
    monkeypatch.setattr(depth_module, "JUDGE_CHUNK", 3)  # several chunks, the last one short
    image = swept_image(setup, phase, sweep.all_m, depth[rows, cols])
    stack = focal_stack_roi(setup, phase, sweep.all_m)
    owner = nearest_plane(depth[rows, cols], sweep.all_m)
    assert torch.equal(image, stack.gather(0, owner[None])[0])


def test_a_colours_plane_propagators_are_released_before_the_next_colour(depth_profile, monkeypatch):
    import gc
    import weakref

    from benchctl.calibration.calibrated import Calibrated
    from benchctl.holograms.depth import compute_depth_scene
    from benchctl.optics.multiplane import MultiPlanePropagator

    held: dict[float, list[weakref.ref]] = {}
    original = MultiPlanePropagator.kernels

    def recorded(self, dtype, device):
        kernels = original(self, dtype, device)
        held.setdefault(self.plan.wavelength_m, []).append(weakref.ref(kernels))
        return kernels

    monkeypatch.setattr(MultiPlanePropagator, "kernels", recorded)
    profile, _, amplitude, depth, _ = _tilted_green(depth_profile)
    result = compute_depth_scene(amplitude, depth, Calibrated(profile), "sgd", iterations=2, colours=["red", "green"],
                                 perceptual=False)
    gc.collect()
    assert result.planes.sweep is not None and [c.channel for c in result.colours] == ["red", "green"]
    red, green = (profile.channel(name).wavelength_nm * 1e-9 for name in ("red", "green"))
    alive = {round(w * 1e9): [ref() is not None for ref in refs] for w, refs in held.items()}
    assert set(alive) == {round(red * 1e9), round(green * 1e9)}
    assert not any(alive[round(red * 1e9)])  # red's sweep went before green's optimisation
    assert any(alive[round(green * 1e9)])  # the last colour keeps its own, as a second frame of it would


@pytest.mark.parametrize("argv, message", [
    (["rgbd:two-planes"], "optics.depth_range_mm"),
    (["rgbd:two-planes", "-m", "gs"], "makes holograms of one plane"),
    (["rgbd:nowhere"], "no bundled scene or scene file"),
    (["chart:siemens", "--planes", "2"], "--planes and --fit-depth are for scenes with depth (rgbd:...)"),
])
def test_generate_refuses_what_it_cannot_show_in_one_line(capsys, tmp_path, small_profile_path, depth_profile, argv,
                                                           message):
    profile = depth_profile
    if message == "optics.depth_range_mm":  # the plain small bench: no depth range
        profile = tmp_path / "flat.toml"
        profile.write_text(depth_profile.read_text().replace("depth_range_mm = [16, 24]\n", ""))
    code, stdout, stderr = _run(capsys, "generate", *argv, "--colours", "green", "-p", str(profile),
                                "-o", str(tmp_path / "o"))
    assert code != 0 and message in stderr
    assert "Traceback" not in stderr and len(stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_planes_must_be_auto_or_a_positive_count(capsys, tmp_path, depth_profile):
    with pytest.raises(SystemExit):
        main(["generate", "rgbd:flat", "--planes", "0", "-p", str(depth_profile), "-o", str(tmp_path / "o")])
    assert "expected 'auto' or a whole number of planes >= 1, got '0'" in capsys.readouterr().err


@pytest.mark.slow
def test_speed_vs_error_puts_the_depth_methods_on_a_scenes_front(tmp_path, depth_profile, monkeypatch):
    import benchctl.benchmarks.speed_vs_error as bench
    from benchctl.benchmarks.speed_vs_error import run_speed_vs_error
    from benchctl.profiles import load_profile

    calls: list[tuple[str, int | None]] = []
    original = bench.compute_depth_scene

    def recorded(*args, **kwargs):
        calls.append((args[3], kwargs.get("iterations")))
        return original(*args, **kwargs)

    monkeypatch.setattr(bench, "compute_depth_scene", recorded)
    lines: list[str] = []
    front = run_speed_vs_error(load_profile(depth_profile), targets=("rgbd:two-planes",), methods=("dpac", "sgd", "gs"),
                               budgets=(3,), colours=["green"], out=lines.append, out_dir=tmp_path)
    assert [(r["method"], r["iterations"]) for r in front] == [("dpac", ""), ("sgd", 3)]
    # each method's first call warms up outside the timed frames (the first Adam step alone took 8 s)
    assert calls == [("dpac", None), ("sgd", 1), ("dpac", None), ("sgd", 3)]
    assert "not running gs on rgbd:two-planes: it makes holograms of one plane" in lines
    assert all(r["psnr_amplitude_db"] > 10 and r["front"] in (True, False) for r in front)
    rows = (tmp_path / "speed_vs_error.csv").read_text().splitlines()
    assert rows[0].split(",")[4] == "planes" and all(row.split(",")[4] == "2" for row in rows[1:])


@pytest.mark.slow
def test_bench_depth_judges_every_plane_count_on_one_stack_and_checks_two_planes_against_2d(depth_profile):
    from benchctl.benchmarks.depth import EVALUATION_PLANES, run_depth_bench
    from benchctl.profiles import load_profile

    lines: list[str] = []
    rows = run_depth_bench(load_profile(depth_profile), scenes=("rgbd:two-planes", "rgbd:flat"), counts=(1, 2),
                           iterations=2, out=lines.append)
    two = [r for r in rows if r["scene"] == "rgbd:two-planes" and "check" not in r]
    assert [r["planes"] for r in two] == [1, 2, "auto"] and [r["count"] for r in two] == [1, 2, 2]
    assert two[2]["planes_m"] == pytest.approx((0.0168, 0.0232)) == two[1]["planes_m"]
    assert all(r["seconds"] > 0 and 5 < r["psnr_db"] < 100 for r in two)
    flat = [r for r in rows if r["scene"] == "rgbd:flat" and "check" not in r]
    assert [r["planes"] for r in flat] == [1, "auto"]  # every K is the one plane of a flat scene
    checks = [r for r in rows if r.get("check") == "two-plane"]
    assert [c["plane_m"] for c in checks] == pytest.approx([0.0168, 0.0232])
    assert any(f"all-in-focus image from {EVALUATION_PLANES} planes" in line for line in lines)
    assert any("auto chose the best K" in line or "from the best" in line for line in lines)
    flat_check = next(r for r in rows if r.get("check") == "flat")
    assert flat_check["same_hologram"] is True and flat_check["psnr_3d_db"] == flat_check["psnr_2d_db"]
    assert flat_check["total_time_ratio"] > 0


def test_the_readme_depth_example_runs_on_a_small_bench(depth_profile):
    import contextlib
    import io
    import re

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    start = text.index("## Scenes with depth (3D holograms)")
    code = re.search(r"```python\n(.*?)```", text[start:], re.S)[1]
    for old, new in (('load_profile("simulated")', f"load_profile({str(depth_profile)!r})"),
                     ("iterations=20", "iterations=3")):
        assert code.count(old) == 1, old
        code = code.replace(old, new)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(code, "README.md", "exec"), {})
    lines = printed.getvalue().splitlines()
    assert "2 plane(s) at 16.80, 23.20 mm" in lines[0]
    assert re.fullmatch(r"mean in-focus PSNR \d+\.\d\d dB over 2 planes", lines[1])


def test_a_sweep_beyond_the_memory_is_one_line_naming_the_fixed_planes_that_fit(capsys, tmp_path, depth_profile,
                                                                                  monkeypatch):
    from benchctl.memory import INTERPRETER_BYTES, depth_estimate, size_text

    profile, _, _, _, choice = _tilted_green(depth_profile)
    depths, planes = len(choice.depths_m), len(choice.planes_m)
    assert choice.sweep is not None and depths > planes == 6
    swept = depth_estimate(profile, depths, planes)
    each = swept.per["depths"] + swept.per["planes"]
    limit = int(INTERPRETER_BYTES + swept.fixed + 3.5 * each)  # three fixed planes fit, not four, nor the sweep
    monkeypatch.setenv("BENCHCTL_MAX_MEMORY", str(limit))
    base = ["generate", "rgbd:tilted", "-m", "sgd", "-n", "2", "--colours", "green", "-p", str(depth_profile)]
    code, _, stderr = _run(capsys, *base, "-o", str(tmp_path / "auto"))
    assert code != 0 and "Traceback" not in stderr and not (tmp_path / "auto").exists()
    assert stderr.strip().splitlines() == [
        f"benchctl: error: --planes auto: a hologram holding {depths} depth(s) for {planes} plane(s) needs about "
        f"{size_text(swept.peak)}, above the {size_text(limit)} of memory here: 3 fixed plane(s) fit (--planes 3, "
        "no sweep) ($BENCHCTL_MAX_MEMORY sets the limit)"]
    code, _, stderr = _run(capsys, *base, "--planes", "4", "-o", str(tmp_path / "four"))
    assert code != 0 and "--planes 4: a hologram holding 4 depth(s) for 4 plane(s)" in stderr
    assert _run(capsys, *base, "--planes", "3", "-o", str(tmp_path / "three"))[0] == 0
    assert len(json.loads((tmp_path / "three" / "metrics.json").read_text())["planes"]) == 3


def test_the_sweep_is_released_before_the_planes_are_judged(depth_profile, monkeypatch):
    import gc
    import weakref

    from benchctl.calibration.calibrated import Calibrated
    from benchctl.holograms.depth import compute_depth_scene
    from benchctl.optics.multiplane import MultiPlanePropagator

    profile, _, amplitude, depth, choice = _tilted_green(depth_profile)
    sweeps: list[weakref.ref] = []
    alive_when_judged: list[bool] = []
    original = MultiPlanePropagator.kernels

    def recorded(self, dtype, device):
        if len(self.plans) == len(choice.planes_m):
            gc.collect()
            alive_when_judged.extend(ref() is not None for ref in sweeps)
        kernels = original(self, dtype, device)
        if len(self.plans) == len(choice.depths_m):
            sweeps.append(weakref.ref(kernels))
        return kernels

    monkeypatch.setattr(MultiPlanePropagator, "kernels", recorded)
    compute_depth_scene(amplitude, depth, Calibrated(profile), "sgd", iterations=2, colours=["green"],
                        perceptual=False)
    assert sweeps and alive_when_judged == [False] * len(sweeps)  # the sweep's kernels were built, then freed


def test_a_benchmark_beyond_the_memory_names_its_size_not_planes_it_does_not_take(capsys, depth_profile,
                                                                                  monkeypatch):
    from benchctl.benchmarks.speed_vs_error import resized_profile
    from benchctl.memory import depth_estimate
    from benchctl.profiles import load_profile

    small = resized_profile(load_profile(depth_profile), (32, 48))
    for colours, command in ((3, ("speed-vs-error", "--methods", "dpac", "--targets", "chart:siemens")),
                             (1, ("depth", "--planes", "1,2", "--scenes"))):
        # rgbd:flat (one plane) fits, rgbd:tilted (a sweep of many depths) does not: refused before flat is computed
        monkeypatch.setenv("BENCHCTL_MAX_MEMORY", str(depth_estimate(small, 2, 2, colours).peak))
        code, stdout, stderr = _run(capsys, "bench", *command, "rgbd:flat", "rgbd:tilted", "--size", "32x48",
                                    "-p", str(depth_profile))
        lines = stderr.strip().splitlines()
        assert code != 0 and len(lines) == 1 and "Traceback" not in stderr
        assert lines[0].startswith("benchctl: error: rgbd:tilted at --size 32x48: a hologram holding ")
        assert lines[0].endswith(" of memory here ($BENCHCTL_MAX_MEMORY sets the limit)")
        assert "--planes" not in stderr and "fixed plane" not in stderr
        assert len(stdout.strip().splitlines()) == (colours == 1) and "PSNR" not in stdout


def test_the_fixed_planes_offered_are_at_most_the_most_a_scene_is_shown_at(depth_profile, monkeypatch):
    from benchctl.errors import BadValueError
    from benchctl.memory import INTERPRETER_BYTES, check_depth_memory, depth_estimate
    from benchctl.optics.planes import MAX_PLANES
    from benchctl.profiles import load_profile

    deep = depth_estimate(load_profile(depth_profile), 1000, 16)  # depths no memory below holds
    each = deep.per["depths"] + deep.per["planes"]
    for fits, offered in ((3, 3), (MAX_PLANES, MAX_PLANES), (40, MAX_PLANES)):
        monkeypatch.setenv("BENCHCTL_MAX_MEMORY", str(int(INTERPRETER_BYTES + deep.fixed + (fits + 0.5) * each)))
        with pytest.raises(BadValueError, match=rf"here: {offered} fixed plane\(s\) fit \(--planes {offered}, no "):
            check_depth_memory(deep, "--planes auto", "--planes {}")
