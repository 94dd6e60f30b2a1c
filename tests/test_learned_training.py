"""Training the learned methods: data, one step, checkpoints (round trip, refusal, resume), the perceptual loss."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import msgspec
import numpy as np
import pytest
import torch

from benchctl.calibration.geometry import grid_profile
from benchctl.calibration.setups import optical_setup
from benchctl.calibration.store import validity
from benchctl.cgh import OpticalSetup
from benchctl.cgh.learned import build_model
from benchctl.cgh.learned.vgg import PerceptualLoss, load_vgg19
from benchctl.cli import main
from benchctl.errors import BadValueError, BenchctlError
from benchctl.holograms.checkpoints import Checkpoint, read_checkpoint
from benchctl.holograms.scene import resolve_method
from benchctl.optics.fitted import FittedOptics
from benchctl.profiles import Profile, load_profile
from benchctl.targets import prepare_target
from benchctl.training.averaging import WeightAverage
from benchctl.training.data import ImageSource, image_sources, procedural_image, split_sources
from benchctl.training.training import (
    ReconstructionLoss,
    TrainSettings,
    load_targets,
    peak_normalised,
    run_train,
    scaled_reconstruction,
    train,
    training_step,
    with_model_calibration,
)


PLANES = {"red": 0, "green": 1, "blue": 2}


def tiny_setup(wavelength_m: float = 520e-9) -> OpticalSetup:
    return OpticalSetup(wavelength_m=wavelength_m, pitch_m=8e-6, distance_m=20e-3, shape=(32, 48), roi=(24, 40))


def test_procedural_images_are_deterministic_varied_and_in_range() -> None:
    a = procedural_image(3, (40, 60))
    assert a.shape == (40, 60, 3) and a.dtype == np.float32
    assert np.array_equal(a, procedural_image(3, (40, 60)))
    assert not np.array_equal(a, procedural_image(4, (40, 60)))
    assert 0.0 <= a.min() and a.max() <= 1.0 and a.std() > 0.05


def test_image_folder_sources_and_a_seeded_validation_split(tmp_path: Path) -> None:
    for i in range(5):
        cv2.imwrite(str(tmp_path / f"img{4 - i}.png"), np.full((8, 10, 3), 40 * i, np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    sources = image_sources(str(tmp_path))
    assert [s.name for s in sources] == [f"img{i}.png" for i in range(5)]
    train_set, val_set = split_sources(sources, 0.2, seed=42)
    assert len(train_set) == 4 and len(val_set) == 1 and val_set[0] not in train_set
    assert split_sources(sources, 0.2, seed=42) == (train_set, val_set)
    assert split_sources(sources, 0.0, seed=42) == (sources, [])
    with pytest.raises(BenchctlError, match="--val-fraction"):
        split_sources(sources, 1.0, seed=42)
    with pytest.raises(BenchctlError, match="no such folder"):
        image_sources(str(tmp_path / "missing"))
    with pytest.raises(BenchctlError, match="procedural:N"):
        image_sources("procedural:0")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BenchctlError, match="no image files"):
        image_sources(str(tmp_path / "empty"))


def test_targets_are_prepared_like_generate_and_flipped_before() -> None:
    grid, roi = (32, 48), (24, 40)
    source = ImageSource("procedural-00002", index=2)
    plain = load_targets([source], grid, roi)
    assert torch.equal(plain[0], prepare_target(procedural_image(2, roi), grid, roi))
    flipped = load_targets([source, source], grid, roi, flips=[(True, False), (False, True)])
    rows, cols = slice(4, 28), slice(4, 44)
    assert torch.equal(flipped[0][:, rows, cols], plain[0][:, rows, cols].flip(-1))
    assert torch.equal(flipped[1][:, rows, cols], plain[0][:, rows, cols].flip(-2))


@pytest.mark.parametrize("name", ["ccnn-dcm4", "holonet-dcm4"])
def test_one_training_step_lowers_the_loss(name: str) -> None:
    setup = tiny_setup()
    torch.manual_seed(0)
    model = build_model(name, setup)
    grid, roi = setup.shape, setup.roi
    amplitude = peak_normalised(load_targets([ImageSource("p", index=0)], grid, roi)[:, 1:2])
    loss_fn = ReconstructionLoss()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-3)

    def loss_now() -> float:
        with torch.no_grad():
            return float(loss_fn(*scaled_reconstruction(model, setup, amplitude)))

    before = loss_now()
    stats = training_step(model, optimiser, setup, amplitude, loss_fn)
    assert stats.loss == pytest.approx(before, rel=1e-4)  # the step reports the loss it started from
    assert 0 < stats.psnr_db < 100
    assert stats.grad_norm > 0 and stats.clamped < 0.5
    assert loss_now() < 0.98 * before


def _checkpoint(setups: dict[str, OpticalSetup], method: str = "holonet-dcm2") -> Checkpoint:
    weights = {}
    for colour, setup in setups.items():
        torch.manual_seed(len(colour))
        model = build_model(method, setup)
        with torch.no_grad():
            for p in model.parameters():
                p.add_(0.01 * torch.randn_like(p))  # GRN gammas and all: no parameter left at its init value
        weights[colour] = model.state_dict()
    return Checkpoint(method=method, geometry={c: s.geometry for c, s in setups.items()}, weights=weights,
                      training={"loss": "mse", "steps": 3},
                      metrics={c: {"val_psnr_amplitude_db": 12.5} for c in setups})


def test_checkpoint_round_trip_float32_exact_and_float16_close(tmp_path: Path) -> None:
    setups = {"red": tiny_setup(680e-9), "green": tiny_setup(520e-9)}
    original = _checkpoint(setups)
    for dtype, tolerance in (("float32", 0.0), ("float16", 2e-3)):
        path = original.save(tmp_path / f"{dtype}.pt", dtype)
        loaded = read_checkpoint(path)
        assert loaded.method == "holonet-dcm2" and loaded.weights_dtype == dtype
        assert loaded.geometry == original.geometry and loaded.training == original.training
        assert loaded.metrics == {"red": {"val_psnr_amplitude_db": 12.5}, "green": {"val_psnr_amplitude_db": 12.5}}
        for colour in setups:
            for key, value in original.weights[colour].items():
                back = loaded.weights[colour][key]
                assert back.dtype == value.dtype  # float16 files come back as float32
                assert torch.allclose(back, value, rtol=tolerance, atol=tolerance * 1e-2), key
        assert path.with_suffix(".json").is_file()
    size32, size16 = (tmp_path / "float32.pt").stat().st_size, (tmp_path / "float16.pt").stat().st_size
    assert size16 < 0.6 * size32
    # The model rebuilt from the file computes what the original computes.
    amplitude = torch.rand(1, 1, 32, 48, generator=torch.Generator().manual_seed(0))
    model = build_model("holonet-dcm2", setups["red"])
    model.load_state_dict(original.weights["red"])
    with torch.no_grad():
        assert torch.allclose(read_checkpoint(tmp_path / "float32.pt").model("red")(amplitude),
                              model.eval()(amplitude))


def test_checkpoint_refuses_another_geometry_naming_each_difference(tmp_path: Path, small_profile_path: Path) -> None:
    profile = load_profile(small_profile_path)
    setups = {ch.name: optical_setup(profile, ch.name) for ch in profile.channels}
    path = _checkpoint(setups, "ccnn").save(tmp_path / "ccnn.pt")
    resolve_method("ccnn", profile, path)  # its own geometry is accepted
    other = small_profile_path.parent / "other.toml"
    other.write_text(small_profile_path.read_text().replace("pitch_um = 8.0", "pitch_um = 3.74")
                     .replace("distance_mm = 20.0", "distance_mm = 70.0").replace('name = "small"', 'name = "other"'))
    with pytest.raises(BenchctlError) as error:
        resolve_method("ccnn", load_profile(other), path)
    message = str(error.value)
    assert "pitch 8 um in the checkpoint, 3.74 um in profile 'other'" in message
    assert "distance 20 mm in the checkpoint, 70 mm in profile 'other'" in message
    assert "wavelength" not in message and "grid" not in message
    with pytest.raises(BenchctlError, match="grid 64x96 in the checkpoint, 32x48 in profile 'small'"):
        resolve_method("ccnn", grid_profile(profile, (32, 48)), path)
    only_red = _checkpoint({"red": setups["red"]}, "ccnn").save(tmp_path / "red.pt")
    with pytest.raises(BenchctlError, match="no model for colour 'green', 'blue'"):
        resolve_method("ccnn", profile, only_red)
    with pytest.raises(BenchctlError, match="holds a ccnn model, not holonet"):
        resolve_method("holonet", profile, path)


def _settings(**changes: object) -> TrainSettings:
    base: dict[str, object] = {"method": "ccnn-dcm4", "data": "procedural:5", "epochs": 2, "lr": 1e-3,
                               "val_fraction": 0.2}
    return TrainSettings(**(base | changes))  # type: ignore[arg-type]


@pytest.mark.slow
def test_training_writes_checkpoints_and_an_interrupted_run_resumes_exactly(tmp_path: Path,
                                                                            small_profile_path: Path) -> None:
    profile = load_profile(small_profile_path)
    def quiet(_: str) -> None:
        pass

    whole = train(profile, _settings(), tmp_path / "whole", PLANES, out=quiet)
    assert whole.steps == 8 and whole.epochs_done == 2
    checkpoint = read_checkpoint(whole.checkpoint)
    assert checkpoint.colours == ["red", "green", "blue"] and checkpoint.method == "ccnn-dcm4"
    assert checkpoint.training["steps"] == 8 and checkpoint.training["data"]["val_images"] == 1
    assert checkpoint.training["command"].startswith("benchctl train --method ccnn-dcm4 --data procedural:5")
    assert [h["epoch"] for h in checkpoint.training["history"]] == [1, 2]
    assert 5 < checkpoint.metrics["green"]["val_psnr_amplitude_db"] < 100
    assert checkpoint.optimisers is None and (tmp_path / "whole" / "ccnn-dcm4.resume.pt").is_file()

    part = train(profile, _settings(max_steps=3), tmp_path / "part", PLANES, out=quiet)
    assert part.steps == 3 and part.epochs_done == 0
    resumed = train(profile, _settings(), tmp_path / "part", PLANES, out=quiet,
                    resume=tmp_path / "part" / "ccnn-dcm4.resume.pt")
    assert resumed.steps == 8
    for colour in ("red", "green", "blue"):
        for key, value in whole.models[colour].state_dict().items():
            assert torch.allclose(resumed.models[colour].state_dict()[key], value, atol=1e-6), (colour, key)

    # a resumed chunk may lower the learning rate (a schedule run in chunks): --lr wins over the saved state's
    lines: list[str] = []
    train(profile, _settings(max_steps=3), tmp_path / "lower", PLANES, out=quiet)
    lowered = train(profile, _settings(lr=_settings().lr / 4, max_steps=4), tmp_path / "lower", PLANES,
                    out=lines.append, resume=tmp_path / "lower" / "ccnn-dcm4.resume.pt")
    assert lowered.steps == 4
    saved = read_checkpoint(tmp_path / "lower" / "ccnn-dcm4.resume.pt").optimisers
    assert {g["lr"] for state in saved.values() for g in state["param_groups"]} == {_settings().lr / 4}
    assert any(f"learning rate {_settings().lr / 4:g} (was {_settings().lr:g})" in line for line in lines)


def test_an_exact_resume_refuses_other_data_seed_batch_or_optical_model(tmp_path: Path,
                                                                        small_profile_path: Path) -> None:
    """`.resume.pt` continues a run exactly: changing what it trains on is refused, naming both values; the weights
    alone (`.pt`) start a new run that may change them (fine-tuning)."""
    profile = load_profile(small_profile_path)
    train(profile, _settings(max_steps=1, colours=("red",)), tmp_path, PLANES, out=lambda _: None)
    resume = tmp_path / "ccnn-dcm4.resume.pt"
    for change, said in (({"data": "procedural:6"}, "--data procedural:6 (the run used procedural:5)"),
                         ({"seed": 7}, "--seed 7 (the run used 42)"),
                         ({"batch_size": 2}, "--batch-size 2 (the run used 1)")):
        with pytest.raises(BadValueError, match=re.escape(said)):
            train(profile, _settings(max_steps=2, colours=("red",), **change), tmp_path, PLANES, out=lambda _: None,
                  resume=resume)
    fitted = msgspec.structs.replace(profile, optics=msgspec.structs.replace(profile.optics, model=_model_file(
        tmp_path, profile)))
    with pytest.raises(BadValueError, match=r"--model-calibration \(the fitted optical model\) a fitted model "
                                            r"\(the run used none\)"):
        train(fitted, _settings(max_steps=2, colours=("red",)), tmp_path, PLANES, out=lambda _: None, resume=resume)
    tuned = train(fitted, _settings(max_steps=1, colours=("red",), data="procedural:6"), tmp_path / "tuned", PLANES,
                  out=lambda _: None, resume=tmp_path / "ccnn-dcm4.pt")
    assert tuned.steps == 1


def _model_file(folder: Path, profile: Profile, geometry: dict[str, object] | None = None) -> Path:
    entry = {**FittedOptics(waist_m=5e-3).to_dict(), "geometry": geometry or validity(profile, "red")}
    path = folder / "optical-model.json"
    path.write_text(json.dumps({"colours": {"red": entry}}))
    return path


def test_training_through_a_model_fitted_for_another_geometry_is_refused(tmp_path: Path,
                                                                        small_profile_path: Path) -> None:
    profile = load_profile(small_profile_path)
    other = validity(profile, "red") | {"distance_m": 0.07}
    path = _model_file(tmp_path, profile, other)
    settings = _settings(colours=("red",), model_calibration=str(path))
    with pytest.raises(BadValueError, match="fitted for another geometry than profile 'small' "
                                            r"\(distance_m 0.07 there, 0.02 here\)"):
        with_model_calibration(profile, settings)
    _model_file(tmp_path, profile)
    assert with_model_calibration(profile, settings).optics.model == path.resolve()


def test_learning_rates_and_data_sizes_outside_their_bounds_are_refused(capsys, tmp_path: Path,
                                                                       small_profile_path: Path) -> None:
    common = ("train", "--method", "ccnn", "--profile", str(small_profile_path), "--out", str(tmp_path))
    for lr in ("1e10", "0", "nan", "-1e-3"):
        code, _, err = _run(capsys, *common, "--data", "procedural:4", f"--lr={lr}")
        assert code == 2 and "--lr must lie in (0, 0.1]" in err, err
    code, _, err = _run(capsys, *common, "--data", "procedural:2000000")
    assert code == 2 and "1 <= N <= 1,000,000" in err
    train_set, val_set = split_sources(image_sources("procedural:100000"), 0.1, 0)
    assert len(val_set) == 256 and len(train_set) == 100_000 - 256  # validation never dwarfs training
    assert not list(tmp_path.glob("*.pt"))


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_train_cli_user_mistakes_are_one_line_errors(capsys, tmp_path: Path, small_profile_path: Path) -> None:
    common = ("train", "--method", "ccnn", "--profile", str(small_profile_path), "--out", str(tmp_path))
    code, _, err = _run(capsys, *common, "--data", "procedural:4", "--loss", "l2-perceptual")
    assert code == 2 and "--loss l2-perceptual needs VGG19 weights: pass --vgg-weights FILE" in err
    code, _, err = _run(capsys, *common, "--data", "procedural:4", "--loss", "l2-perceptual",
                        "--vgg-weights", str(tmp_path / "missing.pth"))
    assert code == 2 and f"--vgg-weights {tmp_path / 'missing.pth'}: no such file" in err
    code, _, err = _run(capsys, *common, "--data", str(tmp_path / "nope"))
    assert code == 2 and "no such folder" in err
    code, _, err = _run(capsys, *common, "--data", "procedural:4", "--val-fraction", "1.5")
    assert code == 2 and "--val-fraction must be in [0, 1)" in err
    code, _, err = _run(capsys, *common, "--data", "procedural:4", "--colours", "purple")
    assert code == 2 and "no laser channel 'purple'" in err
    assert not list(tmp_path.glob("*.pt"))


# torchvision's VGG19 `features`: conv index -> (out, in) channels, written out here independently of the code.
TORCHVISION_VGG19_CONVS = {0: (64, 3), 2: (64, 64), 5: (128, 64), 7: (128, 128), 10: (256, 128), 12: (256, 256),
                           14: (256, 256), 16: (256, 256), 19: (512, 256), 21: (512, 512), 23: (512, 512),
                           25: (512, 512), 28: (512, 512), 30: (512, 512), 32: (512, 512), 34: (512, 512)}


@pytest.mark.slow
def test_perceptual_loss_loads_torchvision_format_weights_and_trains_one_step(
        capsys, tmp_path: Path, small_profile_path: Path) -> None:
    generator = torch.Generator().manual_seed(0)
    state = {}
    for index, (out_channels, in_channels) in TORCHVISION_VGG19_CONVS.items():
        std = (2.0 / (9 * in_channels)) ** 0.5
        state[f"features.{index}.weight"] = (std * torch.randn(out_channels, in_channels, 3, 3,
                                                               generator=generator)).half()
        state[f"features.{index}.bias"] = torch.zeros(out_channels, dtype=torch.float16)
    state["classifier.0.weight"] = torch.zeros(4, 4)  # the classifier is ignored
    weights = tmp_path / "vgg19.pth"
    torch.save(state, weights)

    features = load_vgg19(weights)
    assert torch.equal(features.features[34].weight, state["features.34.weight"].float())
    loss = PerceptualLoss(features)
    a, b = torch.rand(2, 1, 1, 24, 40, generator=generator)
    assert float(loss(a, a)) == 0.0 and float(loss(a, b)) > 0.0

    bad = tmp_path / "bad.pth"
    torch.save({k: v for k, v in state.items() if k != "features.10.weight"}, bad)
    with pytest.raises(BenchctlError, match="missing features.10.weight"):
        load_vgg19(bad)

    out = tmp_path / "out"
    code, stdout, err = _run(capsys, "train", "--method", "ccnn", "--data", "procedural:2", "--profile",
                             str(small_profile_path), "--loss", "l2-perceptual", "--vgg-weights", str(weights),
                             "--max-steps", "1", "--colours", "green", "--out", str(out))
    assert code == 0, err
    checkpoint = read_checkpoint(out / "ccnn.pt")
    assert checkpoint.training["loss"] == "l2-perceptual" and checkpoint.training["perceptual_weight"] == 0.025
    assert checkpoint.training["steps"] == 1 and checkpoint.colours == ["green"]
    assert "validation PSNR" in stdout


@pytest.mark.slow
def test_a_small_grid_training_run_beats_dpac_on_its_own_validation_images(tmp_path: Path) -> None:
    """ccnn on the simulated bench scaled to 68 x 120 (Fresnel number kept), green, 200 steps: its validation PSNR
    passes DPAC's on the same held-out images, which every epoch reports beside it (measured: 21.4 against
    20.0 dB; unquantised phase, ROI, least-squares scaled)."""
    bench = grid_profile(load_profile("simulated"), (68, 120), scale_distance=True)
    settings = TrainSettings(method="ccnn", data="procedural:40", colours=("green",), epochs=10, max_steps=200,
                             lr=3e-3)
    lines: list[str] = []
    result = run_train(bench, settings, tmp_path, out=lines.append)
    green = result.metrics["green"]
    assert green["val_dpac_psnr_amplitude_db"] == pytest.approx(20.0, abs=0.3)
    assert green["val_psnr_amplitude_db"] > green["val_dpac_psnr_amplitude_db"] + 0.5, green
    epoch_lines = [line for line in lines if line.startswith("epoch ")]
    assert len(epoch_lines) == 6 and all("(DPAC 20.02)" in line for line in epoch_lines), epoch_lines  # 5 + a part
    assert "(DPAC on the same images: 20.02 dB" in lines[-2], lines


def test_the_weight_average_is_the_bias_corrected_exponential_average_of_the_steps() -> None:
    model = torch.nn.Linear(2, 1)
    average = WeightAverage(model, decay=0.6)
    assert torch.equal(average.state_dict(model)["weight"], model.weight)  # no step yet: the weights themselves
    seen = []
    for value in (1.0, 3.0, -2.0, 5.0):
        with torch.no_grad():
            model.weight.fill_(value)
        average.update(model)
        seen.append(value)
    t = len(seen)
    expected = sum(0.4 * 0.6 ** (t - 1 - i) * w for i, w in enumerate(seen)) / (1 - 0.6 ** t)
    assert torch.allclose(average.state_dict(model)["weight"], torch.full((1, 2), expected))
    twin = average.averaged(model)
    assert torch.allclose(twin.weight, torch.full((1, 2), expected))
    assert torch.equal(model.weight, torch.full((1, 2), 5.0))  # the model itself trains on
    restored = WeightAverage(model, decay=0.6)
    restored.load_state(average.to_state())
    assert torch.equal(restored.state_dict(model)["weight"], average.state_dict(model)["weight"])
    with pytest.raises(ValueError, match="decay 0.6, this run 0.9"):
        WeightAverage(model, decay=0.9).load_state(average.to_state())


@pytest.mark.slow
def test_training_with_a_weight_average_checkpoints_the_average_and_resumes_it_exactly(
        tmp_path: Path, small_profile_path: Path) -> None:
    profile = load_profile(small_profile_path)
    def quiet(_: str) -> None:
        pass

    whole = train(profile, _settings(ema=0.9), tmp_path / "whole", PLANES, out=quiet)
    checkpoint = read_checkpoint(whole.checkpoint)
    state = read_checkpoint(tmp_path / "whole" / "ccnn-dcm4.resume.pt")
    assert checkpoint.training["weight_average"]["decay"] == 0.9 and "--ema 0.9" in checkpoint.training["command"]
    assert state.averages is not None and state.averages["green"]["count"] == 8
    key = next(k for k, v in checkpoint.weights["green"].items() if v.is_floating_point())
    # the checkpoint holds the average, the resume state the weights that train on; they differ
    assert not torch.allclose(checkpoint.weights["green"][key], state.weights["green"][key])
    assert torch.allclose(checkpoint.weights["green"][key], whole.models["green"].state_dict()[key])

    train(profile, _settings(ema=0.9, max_steps=3), tmp_path / "part", PLANES, out=quiet)
    resumed = train(profile, _settings(ema=0.9), tmp_path / "part", PLANES, out=quiet,
                    resume=tmp_path / "part" / "ccnn-dcm4.resume.pt")
    for colour in ("red", "green", "blue"):
        for name, value in whole.models[colour].state_dict().items():
            assert torch.allclose(resumed.models[colour].state_dict()[name], value, atol=1e-6), (colour, name)


@pytest.mark.slow
def test_a_training_step_that_cannot_fit_in_memory_is_refused_before_anything_starts(
        capsys, tmp_path: Path, small_profile_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The estimate (measured bytes per pixel of the network, times the grid and the batch) against the memory limit:
    `train --size 9000x7000` grew to 23 GB before the kernel killed it; now it is one line."""
    from benchctl.memory import training_estimate

    assert training_estimate("holonet", "holonet", 1, (1088, 1920), 1).peak == pytest.approx(
        8612 * 2**20 + 250 * 2**20, rel=0.001)  # the measured step and the interpreter
    ps2, dcm2 = (training_estimate(m, "holonet", 2, (100, 100), 3) for m in ("holonet-ps2", "holonet-dcm2"))
    assert ps2.per == dcm2.per  # not measured: its family's network with the same factor
    monkeypatch.setenv("BENCHCTL_MAX_MEMORY", "4G")
    common = ("train", "--method", "holonet", "--profile", str(small_profile_path), "--data", "procedural:2",
              "--out", str(tmp_path / "out"))
    code, _, err = _run(capsys, *common, "--size", "1088x1920")
    assert code == 2 and err.startswith("benchctl: error: one training step of holonet on 1088 x 1920 with --batch-size"
                                        " 1 needs about 9.29 GB, above the 4.29 GB of memory here: use a smaller")
    code, _, err = _run(capsys, *common, "--size", "272x480", "--batch-size", "8")
    assert code == 2 and "with --batch-size 8 needs about 4.78 GB" in err and "at most --batch-size 7 fits" in err
    assert not (tmp_path / "out").exists()  # refused before anything was written
    code, stdout, err = _run(capsys, *common, "--max-steps", "1", "--val-fraction", "0")
    assert code == 0, err
    assert "about 289 MB per step" in stdout  # the small profile's 64 x 96 grid, and the interpreter
