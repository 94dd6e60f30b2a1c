"""Networks for scenes with depth (holonet3d and its DCM variants): wiring, counts, random training scenes, their
focal planes, the focal-stack training step, checkpoints and resume."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from benchctl.cgh import OpticalSetup, get_method
from benchctl.cgh.learned import DEPTH_METHODS, DepthHologramNet, build_model, model_info
from benchctl.cgh.learned.models import VARIANTS
from benchctl.cli import main
from benchctl.errors import BadValueError, BenchctlError
from benchctl.holograms.checkpoints import Checkpoint, read_checkpoint
from benchctl.optics import Propagator
from benchctl.optics.focal_stack import focal_stack_loss, in_focus_masks
from benchctl.profiles import load_profile
from benchctl.training.data import ImageSource, image_sources, procedural_scene, loss_planes
from benchctl.training.training import (
    ReconstructionLoss,
    SceneDepth,
    TargetLoader,
    TrainSettings,
    _scaled,
    focal_stack_error,
    peak_normalised,
    train,
    training_step,
)

RANGE = (19e-3, 21e-3)


def tiny_setup(shape: tuple[int, int] = (32, 64)) -> OpticalSetup:
    return OpticalSetup(wavelength_m=520e-9, pitch_m=8e-6, distance_m=20e-3, shape=shape, roi=(24, 48))


def test_the_three_networks_are_registered_as_learned_methods_without_a_2d_refinement() -> None:
    assert DEPTH_METHODS == ("holonet3d", "holonet3d-dcm2", "holonet3d-dcm4")
    for name in DEPTH_METHODS:
        assert get_method(name).needs_checkpoint and get_method(name).family == "holonet3d"
        with pytest.raises(BadValueError, match="unknown hologram method"):
            get_method(f"{name}+sgd")


# At 1088 x 1920 and 2176 x 3840 (the paper's settings per tier for the x2 / x4 LFMN, as holonet-dcm2 / -dcm4).
EXACT = {("holonet3d", (1088, 1920)): 2_868_610, ("holonet3d-dcm2", (1088, 1920)): 3_013_260,
         ("holonet3d-dcm4", (1088, 1920)): 3_114_256, ("holonet3d", (2176, 3840)): 2_868_610,
         ("holonet3d-dcm2", (2176, 3840)): 2_912_960, ("holonet3d-dcm4", (2176, 3840)): 2_964_640}


@pytest.mark.parametrize("key", sorted(EXACT))
def test_parameter_counts_are_the_2d_networks_plus_the_depth_input_of_the_generator(key) -> None:
    name, shape = key
    info = model_info(name, shape)
    assert info["parameters"] == EXACT[key]
    flat = model_info(name.replace("holonet3d", "holonet"), shape)
    r = VARIANTS[name].factor
    # only the generator's first 3x3 conv (16 features, no bias) reads r^2 more channels
    assert info["generator_parameters"] - flat["generator_parameters"] == r * r * 16 * 9
    assert info["encoder_parameters"] == flat["encoder_parameters"]


@pytest.mark.slow
@pytest.mark.parametrize("name", DEPTH_METHODS)
def test_sub_networks_see_amplitude_then_depth_sub_images_and_one_full_definition_propagation_from_the_middle(
        name: str, monkeypatch) -> None:
    setup, r = tiny_setup((64, 128)), VARIANTS[name].factor
    torch.manual_seed(0)
    model = build_model(name, setup, RANGE)
    assert isinstance(model, DepthHologramNet) and model.middle_m == pytest.approx(20e-3)
    seen = []
    model.generator.subnet.register_forward_pre_hook(lambda _m, args: seen.append(args[0]))
    distances = []
    original = Propagator.__call__

    def recording(self: Propagator, field: torch.Tensor) -> torch.Tensor:
        distances.append((self.plan.distance_m, tuple(field.shape)))
        return original(self, field)

    monkeypatch.setattr(Propagator, "__call__", recording)
    amplitude = torch.rand(1, 1, 64, 128)
    depth = 19e-3 + 2e-3 * torch.rand(1, 1, 64, 128, dtype=torch.float64)
    with torch.no_grad():
        phase = model.eval()(amplitude, depth)
    assert phase.shape == (1, 1, 64, 128) and phase.abs().max() <= torch.pi
    normalised = ((depth - 20e-3) / 1e-3).float()
    torch.testing.assert_close(seen[0], F.pixel_unshuffle(torch.cat([amplitude, normalised], 1), r))
    assert seen[0].shape[1] == 2 * r * r
    assert distances == [(pytest.approx(-20e-3), (1, 1, 64, 128))]


@pytest.mark.slow
def test_the_output_depends_on_depth_and_no_depth_is_a_flat_scene_at_the_setup_distance() -> None:
    setup = OpticalSetup(wavelength_m=520e-9, pitch_m=8e-6, distance_m=19.5e-3, shape=(32, 64), roi=(24, 48))
    torch.manual_seed(0)
    model = build_model("holonet3d-dcm2", setup, RANGE).eval()
    amplitude = torch.rand(2, 1, 32, 64)
    with torch.no_grad():
        flat = model(amplitude)
        same = model(amplitude, torch.full((2, 1, 32, 64), 19.5e-3, dtype=torch.float64))
        near = model(amplitude, torch.full((2, 1, 32, 64), 19e-3, dtype=torch.float64))
    torch.testing.assert_close(flat, same)
    assert (flat - near).abs().max() > 1e-3
    with pytest.raises(ValueError, match="depth must be a real map"):
        model(amplitude, torch.zeros(2, 1, 32, 32))
    with pytest.raises(ValueError, match="depth range"):
        build_model("holonet3d", setup, (21e-3, 19e-3))
    # without a range: the setup's distance is the whole range, the depth input is zero
    assert build_model("holonet3d", setup).depth_range_m == (19.5e-3, 19.5e-3)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", ["float32", "float16"])
def test_a_checkpoint_carries_the_depth_range_exactly(tmp_path: Path, dtype: str) -> None:
    setup = tiny_setup()
    torch.manual_seed(0)
    model = build_model("holonet3d-dcm4", setup, (0.0191234567, 0.0207654321))
    path = Checkpoint("holonet3d-dcm4", {"red": setup.geometry}, {"red": model.state_dict()}).save(
        tmp_path / "c.pt", dtype)
    loaded = read_checkpoint(path).model("red")
    assert isinstance(loaded, DepthHologramNet)
    assert loaded.depth_range_m == pytest.approx((0.0191234567, 0.0207654321), abs=1e-9)
    amplitude, depth = torch.rand(1, 1, 32, 64), torch.full((1, 1, 32, 64), 0.02, dtype=torch.float64)
    with torch.no_grad():
        expected = model.eval()(amplitude, depth)
        torch.testing.assert_close(loaded(amplitude, depth), expected, atol=1e-6 if dtype == "float32" else 0.1,
                                   rtol=0)
    # a 2D network's weights are not a depth network's
    flat = build_model("holonet-dcm4", setup).state_dict()
    with pytest.raises(RuntimeError, match="depth_range_nm"):
        build_model("holonet3d-dcm4", setup).load_state_dict(flat)


def test_procedural_scenes_are_deterministic_layered_occluded_and_in_range() -> None:
    image, depth = procedural_scene(3, (48, 80))
    again, depth_again = procedural_scene(3, (48, 80))
    assert np.array_equal(image, again) and np.array_equal(depth, depth_again)
    assert image.shape == (48, 80, 3) and image.dtype == np.float32 and depth.shape == (48, 80)
    assert 0 <= image.min() and image.max() <= 1
    kinds = set()
    for index in range(24):
        image, depth = procedural_scene(index, (48, 80))
        assert 0 <= depth.min() and depth.max() <= 1
        distinct = len(np.unique(depth))
        kinds.add("layered" if distinct <= 5 else "continuous")
        assert distinct >= 2 or depth.std() == 0
    assert kinds == {"layered", "continuous"}
    assert not np.array_equal(procedural_scene(0, (48, 80))[1], procedural_scene(1, (48, 80))[1])
    # a shape nearer the camera hides what is behind: where depth is largest the texture is the shape's
    sources = image_sources("procedural-rgbd:3")
    assert [s.name for s in sources] == ["procedural-rgbd-00000", "procedural-rgbd-00001", "procedural-rgbd-00002"]
    assert np.array_equal(sources[1].load((48, 80)), procedural_scene(1, (48, 80))[0])
    with pytest.raises(BadValueError, match="procedural-rgbd:N"):
        image_sources("procedural-rgbd:0")


def test_a_picture_without_depth_lies_on_a_ground_plane() -> None:
    image, depth = ImageSource("p", index=2).load_scene((12, 20))
    assert image.shape == (12, 20, 3)
    assert np.allclose(depth[:, 0], np.linspace(0, 1, 12)) and np.allclose(depth, depth[:, :1])


def test_scene_planes_are_a_layered_scenes_own_depths_else_jittered_bin_centres() -> None:
    layered = np.array([[0.2, 0.2, 0.7], [0.9, 0.7, 0.2]])
    assert loss_planes(layered, 5) == (0.2, 0.7, 0.9)
    assert loss_planes(layered, 5, jitter=0.4) == (0.2, 0.7, 0.9)
    ramp = np.linspace(1.0, 2.0, 101)
    assert loss_planes(ramp, 4) == pytest.approx((1.125, 1.375, 1.625, 1.875))
    assert loss_planes(ramp, 4, jitter=-0.5) == pytest.approx((1.0, 1.25, 1.5, 1.75))
    assert loss_planes(ramp, 4, jitter=0.5) == pytest.approx((1.25, 1.5, 1.75, 2.0))
    assert loss_planes(np.full(3, 1.5), 4) == (1.5,)
    with pytest.raises(ValueError):
        loss_planes(ramp, 0)
    with pytest.raises(ValueError):
        loss_planes(ramp, 3, jitter=0.6)


def test_scene_targets_flip_image_and_depth_together_and_take_their_planes_on_the_roi() -> None:
    setup = tiny_setup()
    loader = TargetLoader(setup.shape, setup.roi, RANGE, 3)
    source = ImageSource("s", index=4, scene=True)
    (plain, scenes), (flipped, flipped_scenes) = loader([source]), loader([source], [(True, True)], [0.25])
    rows, cols = setup.roi_slices
    assert plain.shape == (1, 3, 32, 64) and scenes.depth_m.shape == (1, 1, 32, 64)
    assert scenes.depth_m.dtype == torch.float64
    image, relative = procedural_scene(4, setup.roi)
    torch.testing.assert_close(scenes.depth_m[0, 0, rows, cols], torch.from_numpy(19e-3 + 2e-3 * relative))
    torch.testing.assert_close(flipped[0][:, rows, cols], plain[0][:, rows, cols].flip(-1, -2))
    torch.testing.assert_close(flipped_scenes.depth_m[0, 0], scenes.depth_m[0, 0].flip(-1, -2))
    assert plain[0, :, :rows.start].abs().max() == 0  # the image is dark outside the ROI ...
    assert torch.equal(scenes.depth_m[0, 0, 0, cols], scenes.depth_m[0, 0, rows.start, cols])  # ... its depth not
    assert scenes.planes_m[0] == loss_planes(scenes.depth_m[0, 0, rows, cols].numpy(), 3)
    assert len(flipped_scenes.planes_m[0]) <= 3


def test_a_flat_scene_on_one_plane_has_the_2d_loss() -> None:
    """One plane at the setup's distance with every pixel in focus there: the focal-stack loss is the 2D training
    loss (MSE on the ROI after the least-squares scale) and its PSNR the 2D PSNR."""
    setup = tiny_setup()
    amplitude = peak_normalised(torch.rand(2, 1, 32, 64) * F.pad(torch.ones(1, 1, 24, 48), (8, 8, 4, 4)))
    phase = torch.rand(2, 1, 32, 64) * 6 - 3
    scenes = SceneDepth(torch.full((2, 1, 32, 64), 20e-3, dtype=torch.float64), ((20e-3,), (20e-3,)))
    losses, psnr_db = focal_stack_error(phase, setup, amplitude, scenes)
    for b in range(2):
        recon, target = _scaled(phase[b:b + 1], setup, amplitude[b:b + 1])
        assert float(losses[b]) == pytest.approx(float(ReconstructionLoss()(recon, target)), rel=1e-4)
        assert float(psnr_db[b]) == pytest.approx(float(-10 * torch.log10(losses[b])), rel=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("name", DEPTH_METHODS)
def test_one_focal_stack_step_lowers_the_loss(name: str) -> None:
    setup = tiny_setup()
    loader = TargetLoader(setup.shape, setup.roi, RANGE, 4)
    targets, scenes = loader([ImageSource("s", index=1, scene=True)])
    assert scenes is not None and len(scenes.planes_m[0]) >= 2
    amplitude = peak_normalised(targets[:, 1:2])
    torch.manual_seed(0)
    model = build_model(name, setup, RANGE)
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-3)

    def loss_now() -> float:
        model.eval()
        with torch.no_grad():
            return float(focal_stack_error(model(amplitude, scenes.depth_m), setup, amplitude, scenes)[0].mean())

    before = loss_now()
    stats = training_step(model, optimiser, setup, amplitude, ReconstructionLoss(), scenes)
    assert 0 < stats.psnr_db < 100 and stats.grad_norm > 0
    for _ in range(3):
        training_step(model, optimiser, setup, amplitude, ReconstructionLoss(), scenes)
    assert loss_now() < before
    # the stack's loss is the masked one, every plane where the scene is in focus there
    rows, cols = setup.roi_slices
    model.eval()
    with torch.no_grad():
        phase = model(amplitude, scenes.depth_m)
        recon = setup.reconstruct_planes_roi(phase[0, 0], scenes.planes_m[0])
        masks = in_focus_masks(scenes.depth_m[0, 0, rows, cols], scenes.planes_m[0])
        expected = focal_stack_loss(recon, amplitude[0, 0, rows, cols], masks)
    assert float(focal_stack_error(phase, setup, amplitude, scenes)[0][0]) == pytest.approx(float(expected))


DEPTH_PROFILE_LINE = "depth_range_mm = [19.0, 21.0]\n"


@pytest.mark.slow
def test_depth_training_checkpoints_its_range_and_resumes_exactly(tmp_path: Path, small_profile_path: Path) -> None:
    text = small_profile_path.read_text().replace("roi = [48, 80]\n", "roi = [48, 80]\n" + DEPTH_PROFILE_LINE)
    small_profile_path.write_text(text)
    profile = load_profile(small_profile_path)
    settings = TrainSettings(method="holonet3d-dcm4", data="procedural-rgbd:4+procedural:1", epochs=2, lr=1e-3,
                             val_fraction=0.2, colours=("green",), planes=3)
    quiet: list[str] = []
    whole = train(profile, settings, tmp_path / "whole", {"green": 1}, out=quiet.append)
    checkpoint = read_checkpoint(whole.checkpoint)
    assert checkpoint.training["depth_range_mm"] == pytest.approx([19.0, 21.0])
    assert checkpoint.training["planes"] == 3 and "--planes 3" in checkpoint.training["command"]
    metrics = checkpoint.metrics["green"]
    assert 5 < metrics["val_psnr_amplitude_db"] < 100 and 5 < metrics["val_dpac_psnr_amplitude_db"] < 100
    assert 0 < metrics["val_ssim_amplitude"] <= 1
    assert checkpoint.model("green").depth_range_m == pytest.approx((19e-3, 21e-3))

    part = train(profile, TrainSettings(**{**settings.__dict__, "max_steps": 3}), tmp_path / "part", {"green": 1},
                 out=quiet.append)
    assert part.steps == 3
    resume = tmp_path / "part" / "holonet3d-dcm4.resume.pt"
    resumed = train(profile, settings, tmp_path / "part", {"green": 1}, out=quiet.append, resume=resume)
    assert resumed.steps == whole.steps == 8
    for key, value in whole.models["green"].state_dict().items():
        assert torch.allclose(resumed.models["green"].state_dict()[key], value, atol=1e-6), key
    with pytest.raises(BadValueError, match=r"--planes 4 \(the run used 3\)"):
        train(profile, TrainSettings(**{**settings.__dict__, "planes": 4}), tmp_path / "part", {"green": 1},
              out=quiet.append, resume=resume)


def test_depth_training_mistakes_are_one_line_errors(capsys, tmp_path: Path, small_profile_path: Path) -> None:
    base = ["train", "--method", "holonet3d", "--data", "procedural-rgbd:4", "--profile", str(small_profile_path),
            "--out", str(tmp_path)]
    cases = {
        ("--fresnel-scaled",): "--fresnel-scaled scales the bench to a smaller grid",
        ("--loss", "l2-perceptual", "--vgg-weights", "x.pth"): "trains on the focal-stack loss",
        ("--planes", "17"): "--planes must lie between 1 and 16",
        (): "shows one plane only; set optics.depth_range_mm",
    }
    for extra, message in cases.items():
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    with pytest.raises(BenchctlError, match="shows one plane only"):
        train(load_profile(small_profile_path), TrainSettings(method="holonet3d", data="procedural-rgbd:2"),
              tmp_path, {"red": 0})


def _depth_checkpoint(path: Path, method: str, seed: int, depth_range: tuple[float, float] = (1.9e-3, 2.1e-3)) -> Path:
    """Random weights on a bench whose Fresnel number (about 190) makes sharp images on a 32 x 64 grid."""
    setup = OpticalSetup(wavelength_m=680e-9, pitch_m=8e-6, distance_m=2e-3, shape=(32, 64), roi=(24, 48))
    torch.manual_seed(seed)
    model = build_model(method, setup, depth_range)
    return Checkpoint(method, {"red": setup.geometry}, {"red": model.state_dict()},
                      training={"seed": seed}).save(path)


@pytest.mark.slow
def test_the_held_out_bench_scores_networks_dpac_and_multi_plane_sgd_per_plane_over_seeds(
        tmp_path: Path, small_profile_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from benchctl.benchmarks import learned_depth
    from benchctl.benchmarks.learned_depth import DPAC_LABEL, SGD_LABEL, run_learned_depth_bench

    budgets: list[int | None] = []
    made = learned_depth.sgd_method

    def recorded(*args: Any, **kwargs: Any) -> Callable[..., torch.Tensor]:
        sgd = made(*args, **kwargs)

        def run(*args: Any, iterations: int | None = None, **kwargs: Any) -> torch.Tensor:
            budgets.append(iterations)
            return sgd(*args, iterations=iterations, **kwargs)
        return run

    monkeypatch.setattr(learned_depth, "sgd_method", recorded)
    paths = [_depth_checkpoint(tmp_path / f"{seed}.pt", "holonet3d-dcm4", seed) for seed in (1, 2)]
    lines: list[str] = []
    rows = run_learned_depth_bench(load_profile(small_profile_path), paths, scenes=["rgbd:two-planes", "rgbd:tilted"],
                                   planes=3, sgd_iterations=30, out_dir=tmp_path / "out", out=lines.append)
    two = [r for r in rows if r["scene"] == "rgbd:two-planes"]
    assert sorted({r["plane_mm"] for r in two}) == pytest.approx([1.92, 2.08])  # its layers at 10 % and 90 %
    tilted = [r for r in rows if r["scene"] == "rgbd:tilted" and r["method"] == SGD_LABEL]
    assert [r["plane"] for r in tilted] == [0, 1, 2]  # continuous: 3 planes over its span
    assert {(r["method"], r["seed"]) for r in rows} == {(DPAC_LABEL, ""), (SGD_LABEL, ""), ("holonet3d-dcm4", 1),
                                                         ("holonet3d-dcm4", 2)}

    def mean(method: str, scene: str) -> float:
        return next(r["mean_psnr_amplitude_db"] for r in rows if r["method"] == method and r["scene"] == scene)

    for scene in ("rgbd:two-planes", "rgbd:tilted"):
        assert mean(SGD_LABEL, scene) > mean(DPAC_LABEL, scene) + 1  # it starts from DPAC and keeps its best
    # per scene one untimed iteration first (a process's first Adam step took seconds), then the budget
    assert budgets == [1, 30, 1, 30]
    summary = (tmp_path / "out" / "learned_depth_summary.csv").read_text().splitlines()
    network_all = [line for line in summary if line.startswith("all scenes,holonet3d-dcm4,2,")]
    assert len(network_all) == 1
    per_seed = [np.mean([r["mean_psnr_amplitude_db"] for r in rows if r["seed"] == seed and r["plane"] == 0])
                for seed in (1, 2)]
    assert float(network_all[0].split(",")[3]) == pytest.approx(np.mean(per_seed), abs=1e-6)
    assert any(line.startswith("all scenes") and "+-" in line for line in lines)
    other = _depth_checkpoint(tmp_path / "other.pt", "holonet3d", 1, (1.95e-3, 2.05e-3))
    with pytest.raises(BadValueError, match="another bench or depth range"):
        run_learned_depth_bench(load_profile(small_profile_path), [paths[0], other])


@pytest.mark.slow
def test_the_device_table_measures_every_network_in_one_process_with_ratios(small_profile_path: Path) -> None:
    from benchctl.benchmarks.learned import run_device_table

    text = small_profile_path.read_text().replace("roi = [48, 80]\n", "roi = [48, 80]\n" + DEPTH_PROFILE_LINE)
    small_profile_path.write_text(text)
    rows = run_device_table(load_profile(small_profile_path), grids=[(32, 64)], methods=DEPTH_METHODS, repeats=1,
                            out=lambda _: None)
    assert [r["method"] for r in rows] == list(DEPTH_METHODS)
    assert [r["parameters"] for r in rows] == [model_info(m, (32, 64))["parameters"] for m in DEPTH_METHODS]
    assert rows[0]["speedup"] == rows[0]["cpu_speedup"] == 1.0
    for row in rows:
        assert row["inference_seconds"] > 0 and row["inference_cpu_seconds"] > 0
        assert row["speedup"] == pytest.approx(rows[0]["inference_seconds"] / row["inference_seconds"])
        assert row["cpu_speedup"] == pytest.approx(rows[0]["inference_cpu_seconds"] / row["inference_cpu_seconds"])


@pytest.mark.slow
def test_the_device_table_says_out_of_memory_when_the_step_reports_it(
        small_profile_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """On CUDA, training_step_memory returns {"out_of_memory": True} (it no longer raises): the table's row says so
    (it was a KeyError on 'peak_bytes')."""
    from benchctl.benchmarks import learned
    from benchctl.benchmarks.learned import OUT_OF_MEMORY, run_device_table

    text = small_profile_path.read_text().replace("roi = [48, 80]\n", "roi = [48, 80]\n" + DEPTH_PROFILE_LINE)
    small_profile_path.write_text(text)
    measured = learned.training_step_memory

    def refused_for_the_undivided(method: str, *args: object, **kwargs: object) -> dict[str, object]:
        if method == "holonet3d":
            return {"out_of_memory": True, "total_bytes": 1}
        return measured(method, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(learned, "training_step_memory", refused_for_the_undivided)
    rows = run_device_table(load_profile(small_profile_path), grids=[(32, 64)], methods=DEPTH_METHODS[:2],
                            repeats=1, out=lambda _: None)
    assert rows[0]["result"] == OUT_OF_MEMORY and "train_step_peak_mib" not in rows[0]
    # measured (in a process that freed more before, the step's peak over the resident set can be 0 MiB)
    assert "result" not in rows[1] and rows[1]["train_step_peak_mib"] >= 0 and rows[1]["inference_seconds"] > 0


@pytest.mark.slow
def test_generate_makes_a_scene_with_depth_with_a_trained_3d_network(capsys, tmp_path: Path,
                                                                     small_profile_path: Path) -> None:
    """`generate rgbd:` runs the network on the scene's image and depth map (it was refused: a learned method had no
    focal-stack entry), on one plane too, and refuses a scene deeper than the network's range in one line."""
    import cv2

    from benchctl.calibration.setups import optical_setup
    from benchctl.cgh.method import wrap_phase
    from benchctl.devices.slm import slm_for
    from benchctl.scenes import load_scene, prepare_scene

    text = small_profile_path.read_text().replace("roi = [48, 80]\n", "roi = [48, 80]\n" + DEPTH_PROFILE_LINE)
    small_profile_path.write_text(text)
    profile = load_profile(small_profile_path)
    setup = optical_setup(profile, "red")
    torch.manual_seed(0)
    model = build_model("holonet3d-dcm2", setup, (19e-3, 21e-3))
    path = Checkpoint("holonet3d-dcm2", {"red": setup.geometry}, {"red": model.state_dict()}).save(tmp_path / "n.pt")
    model.eval()
    for scene, planes in (("rgbd:two-planes", "2"), ("rgbd:flat", "1")):
        out = tmp_path / scene.split(":")[1]
        code = main(["generate", scene, "-m", "holonet3d-dcm2", "--checkpoint", str(path), "--colours", "red",
                     "--planes", planes, "-p", str(small_profile_path), "-o", str(out)])
        assert code == 0, capsys.readouterr().err
        assert len(json.loads((out / "metrics.json").read_text())["planes"]) == int(planes)
        amplitude, depth = prepare_scene(load_scene(scene, setup.roi, (19e-3, 21e-3)), setup.shape, setup.roi)
        with torch.no_grad():
            phase = wrap_phase(model(amplitude[0][None, None] / amplitude[0].max(), depth[None, None])[0, 0])
        written = cv2.imread(str(out / "phase_red.png"), cv2.IMREAD_UNCHANGED)
        # inference runs on channels-last weights (another summation order): a gray level may round the other way
        steps = (written.astype(int) - slm_for(profile).encode(phase, "red").astype(int)) % 256
        assert np.all((steps <= 1) | (steps == 255)) and np.mean(steps == 0) > 0.99
    narrow = build_model("holonet3d", setup, (19.5e-3, 20.5e-3))
    other = Checkpoint("holonet3d", {"red": setup.geometry}, {"red": narrow.state_dict()}).save(tmp_path / "m.pt")
    code = main(["generate", "rgbd:two-planes", "-m", "holonet3d", "--checkpoint", str(other), "--colours", "red",
                 "-p", str(small_profile_path), "-o", str(tmp_path / "deep")])
    err = capsys.readouterr().err
    assert code != 0 and "lies outside the 19.5 .. 20.5 mm holonet3d was trained for" in err
    assert "Traceback" not in err
