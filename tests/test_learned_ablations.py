"""The paper's ablation variants in use (train, checkpoint, generate), combined training data, and the
`bench reproduce` command end to end on a tiny grid."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from benchctl.benchmarks import reproduce_job
from benchctl.benchmarks.reproduce import DEFAULT_METHODS, new_plan, reproduce_command
from benchctl.benchmarks.reproduce_job import Evaluation, doubling_gain, flat_doublings, run_job
from benchctl.benchmarks.reproduce_report import PAPER, comparisons, seed_curve
from benchctl.cli import main
from benchctl.errors import BadValueError, BenchctlError
from benchctl.holograms.checkpoints import read_checkpoint
from benchctl.profiles import load_profile
from benchctl.targets import photo_specs
from benchctl.training.data import image_sources
from benchctl.training.health import StepStats

ABLATIONS = ("holonet-ps2", "holonet-ps4", "holonet-lowdef2", "holonet-dcm2-nolfm", "holonet-dcm2-noeccm",
             "holonet-dcm2-nogrn")


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.slow
@pytest.mark.parametrize("name", ABLATIONS)
def test_ablation_trains_saves_loads_and_generates(name: str, capsys, tmp_path: Path, small_profile_path: Path) -> None:
    ckpt = tmp_path / "ckpt"
    code, _, err = _run(capsys, "train", "--method", name, "--data", "procedural:2", "--profile",
                        str(small_profile_path), "--colours", "red", "--epochs", "1", "--max-steps", "1",
                        "--val-fraction", "0", "--out", str(ckpt))
    assert code == 0, err
    checkpoint = read_checkpoint(ckpt / f"{name}.pt")
    assert checkpoint.method == name and checkpoint.training["steps"] == 1
    assert checkpoint.model("red") is not None  # the weights fit the architecture they were saved from
    out = tmp_path / "gen"
    code, stdout, err = _run(capsys, "generate", "chart:bars", "--method", name, "--checkpoint",
                             str(ckpt / f"{name}.pt"), "--colours", "red", "-p", str(small_profile_path), "-o",
                             str(out))
    assert code == 0, err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == name
    assert (out / "phase_red.png").is_file()


def test_training_data_combines_procedural_images_and_training_photographs() -> None:
    sources = image_sources("procedural:3+photos:train")
    assert [s.name for s in sources[:3]] == ["procedural-00000", "procedural-00001", "procedural-00002"]
    assert [s.name for s in sources[3:]] == photo_specs("train")
    assert not set(photo_specs("eval")) & {s.name for s in sources}  # held-out photographs never train
    image = sources[3].load((40, 60))
    assert image.ndim == 3 and image.shape[2] == 3 and 0.0 <= image.min() and image.max() <= 1.0
    for bad, match in (("photos:all", "photos:train or photos:eval"), ("procedural:2+", "empty part")):
        with pytest.raises(BadValueError, match=match):
            image_sources(bad)


@pytest.mark.slow
def test_reproduce_runs_end_to_end_and_writes_table_comparisons_curves_and_plots(capsys, tmp_path: Path,
                                                                                 small_profile_path: Path) -> None:
    out = tmp_path / "repro"
    code, stdout, err = _run(capsys, "bench", "reproduce", "--profile", str(small_profile_path), "--size", "32x48",
                             "--methods", "holonet-ps2,ccnn,ccnn-dcm4", "--seeds", "1,2", "--max-steps", "3",
                             "--min-steps", "2", "--data", "procedural:2", "--jobs", "2", "--out", str(out))
    assert code == 0, err
    plan = json.loads((out / "plan.json").read_text())
    assert [j["name"] for j in plan["jobs"]] == ["holonet-ps2-s1", "ccnn-s1", "ccnn-dcm4-s1", "ccnn-s2",
                                                 "ccnn-dcm4-s2"]  # first seeds first; the ablation once
    rows = {r["method"]: r for r in csv.DictReader((out / "reproduction.csv").open())}
    assert list(rows) == ["holonet-ps2", "ccnn", "ccnn-dcm4"]
    assert [rows[m]["seeds"] for m in rows] == ["1", "2", "2"]
    for row in rows.values():
        assert row["ended_by"] == "step cap" and int(row["steps"]) == 3
        assert 0 < float(row["psnr_db"]) < 60 and 0 < float(row["ssim"]) <= 1
        assert float(row["paper_psnr_db"]) == PAPER[row["method"]][0]
        assert float(row["train_step_peak_mib"]) > 0 and float(row["inference_seconds"]) > 0
    assert float(rows["ccnn-dcm4"]["psnr_db_sd"]) > 0  # two seeds train two different networks
    assert rows["ccnn"]["baseline"] == "ccnn" and float(rows["ccnn"]["delta_db"]) == 0.0
    assert rows["holonet-ps2"]["baseline"] == ""  # holonet, its baseline, was not run
    comparison = next(csv.DictReader((out / "comparisons.csv").open()))
    assert comparison["method"] == "ccnn-dcm4" and int(comparison["pairs"]) == 2
    assert float(comparison["here_db"]) == pytest.approx(float(rows["ccnn-dcm4"]["psnr_db"])
                                                         - float(rows["ccnn"]["psnr_db"]), abs=2e-3)
    curves = list(csv.DictReader((out / "curves.csv").open()))
    assert [(c["job"], int(c["step"])) for c in curves] == [(j["name"], 3) for j in plan["jobs"]]  # the cap
    report = (out / "reproduction.md").read_text()
    assert "| method | seeds | ended by |" in report and "| dpac (classical reference) |" in report
    scored = list(csv.DictReader((out / "per_image_seeds.csv").open()))  # each job's held-out images
    assert sorted((r["job"], r["image"]) for r in scored) == sorted((j["name"], image) for j in plan["jobs"]
                                                                    for image in photo_specs("eval"))
    means = {(r["image"], r["method"]): float(r["psnr_db"]) for r in csv.DictReader((out / "per_image.csv").open())}
    coffee = [float(r["psnr_db"]) for r in scored if r["method"] == "ccnn" and r["image"] == "photo:coffee"]
    assert len(coffee) == 2 and means["photo:coffee", "ccnn"] == pytest.approx(sum(coffee) / 2)
    assert "benchctl bench reproduce" in report and "| CCNN x4 about equal to CCNN |" in report
    for name in ("psnr_vs_step.png", "psnr_vs_seconds.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, stdout, err = _run(capsys, "bench", "reproduce", "--resume", str(out), "--no-memory")
    assert code == 0, err
    assert "5 of 5 jobs finished; training 0" in stdout  # a finished job is never retrained
    code, _, err = _run(capsys, "bench", "reproduce", "--profile", str(small_profile_path), "--out", str(out))
    assert code == 2 and "--resume" in err  # a run folder is never started twice


@pytest.mark.slow
def test_an_interrupted_reproduction_job_continues_exactly(tmp_path: Path, small_profile_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    settings = dict(size=(32, 48), methods=["ccnn-dcm4"], seeds=[3], data="procedural:2", max_steps=6, min_steps=4,
                    first_evaluation=2, iris_test=False)
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    profile = load_profile(str(small_profile_path))
    for folder in (whole, parts):
        new_plan(folder, profile, **settings)
    expected = run_job(whole, "ccnn-dcm4-s3", out=lambda _: None)
    monkeypatch.setattr(reproduce_job, "SAVE_EVERY_S", 0.0)  # a state after every step
    calls = {"n": 0}
    step = reproduce_job.training_step

    def interrupted(*args: object, **kwargs: object) -> object:
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return step(*args, **kwargs)

    monkeypatch.setattr(reproduce_job, "training_step", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_job(parts, "ccnn-dcm4-s3", out=lambda _: None)
    monkeypatch.setattr(reproduce_job, "training_step", step)
    lines: list[str] = []
    resumed = run_job(parts, "ccnn-dcm4-s3", out=lines.append)
    assert lines[0] == "ccnn-dcm4-s3: resuming at step 4"
    assert [e | {"cpu_seconds": 0, "wall_seconds": 0} for e in resumed["curve"]] == \
        [e | {"cpu_seconds": 0, "wall_seconds": 0} for e in expected["curve"]]
    assert resumed["reason"] == expected["reason"] == "step cap" and resumed["steps"] == 6


def test_a_claim_is_read_where_training_ended_and_where_validation_was_best() -> None:
    """A batch-1 run can end on a dip: the comparison gives both readings, paired by seed."""
    def run(seed: int, *evaluations: tuple[float, float]) -> dict:
        return {"seed": seed, "curve": [{"val_psnr": v, "psnr": p} for v, p in evaluations]}

    groups = {("holonet-dcm2", True): [run(1, (20.0, 30.0), (10.0, 25.0)), run(2, (12.0, 27.0), (13.0, 28.0))],
              ("holonet", True): [run(1, (5.0, 28.0), (6.0, 29.0)), run(2, (7.0, 26.0), (6.0, 30.0))]}
    (claim,) = comparisons(groups)
    assert claim["claim"] == "x2 about equal to HoloNet" and claim["pairs"] == 2
    assert claim["here_db"] == pytest.approx((25 + 28) / 2 - (29 + 30) / 2)  # end: -3
    assert claim["best_val_db"] == pytest.approx((30 + 28) / 2 - (29 + 26) / 2)  # best validation: +1.5
    assert claim["per_seed_db"] == "-4.00 -2.00"
    # 95 % t-interval of (-4, -2): mean -3, t(0.975, 1 dof) = 12.706, sd sqrt(2), n 2
    assert (claim["ci_low_db"], claim["ci_high_db"]) == pytest.approx((-3 - 12.7062, -3 + 12.7062), abs=1e-3)
    assert claim["paper_db"] == pytest.approx(PAPER["holonet-dcm2"][0] - PAPER["holonet"][0])
    assert claim["verdict"] == "not resolved"  # the paper's +0.36 lies inside an interval far wider than +-1 dB


def test_a_seed_that_stopped_early_leaves_the_curve_to_the_others() -> None:
    stalled = {"curve": [{"step": 16, "psnr": 14.0}, {"step": 21, "psnr": 14.5}]}
    trained = [{"curve": [{"step": s, "psnr": p} for s, p in zip((16, 21, 32, 45), (15.0, 16.0, 20.0, 24.0))]},
               {"curve": [{"step": s, "psnr": p} for s, p in zip((16, 21, 32, 45), (17.0, 18.0, 22.0, 26.0))]}]
    x, values, stopped = seed_curve([stalled, *trained], "step")
    assert x == [16, 21, 32, 45] and stopped == 1
    assert values == [[14.0, 15.0, 17.0], [14.5, 16.0, 18.0], [20.0, 22.0], [24.0, 26.0]]
    assert seed_curve(trained, "step")[2] == 0


def test_a_job_that_stops_learning_ends_there_and_says_why(tmp_path: Path, small_profile_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    new_plan(tmp_path, load_profile(str(small_profile_path)), size=(32, 48), methods=["ccnn"], seeds=[1],
             data="procedural:2", max_steps=64, min_steps=32, first_evaluation=4, iris_test=False)
    monkeypatch.setattr(reproduce_job, "training_step", lambda *args, **kwargs: StepStats(0.1, 10.0, 0.0, 1.0))
    lines: list[str] = []
    done = run_job(tmp_path, "ccnn-s1", out=lines.append)
    assert done["reason"] == "stopped learning" and done["steps"] == 10  # ten steps at the clamp with no gradient
    assert lines[-2].startswith("ccnn-s1: stopped learning at step 10: for 10 steps the gradient was 0")
    assert [e["step"] for e in done["curve"]] == [4, 6, 8, 10]  # evaluated where it stopped
    assert json.loads((tmp_path / "jobs" / "ccnn-s1" / "done.json").read_text())["reason"] == "stopped learning"


def test_reproduction_settings_are_checked_before_anything_trains(tmp_path: Path, small_profile_path: Path) -> None:
    profile = load_profile(str(small_profile_path))
    for kwargs, match in (({"lr": float("nan")}, "--lr"), ({"lr": 1e10}, "--lr"), ({"size": (9000, 9000)}, "--size"),
                          ({"methods": ["holonet-dcm3"]}, "holonet-dcm3"), ({"min_steps": 10, "max_steps": 5},
                                                                           "--min-steps"),
                          ({"colour": "purple"}, "purple"), ({"min_gain_db": float("inf")}, "--min-gain")):
        with pytest.raises(BenchctlError, match=match):
            new_plan(tmp_path / "x", profile, **kwargs)
        assert not (tmp_path / "x" / "plan.json").exists()


def test_reproduce_user_mistakes_are_one_line_errors(capsys, small_profile_path: Path, tmp_path: Path) -> None:
    assert set(DEFAULT_METHODS) <= set(PAPER)
    code, _, err = _run(capsys, "bench", "reproduce", "--profile", str(small_profile_path), "--methods",
                        "holonet-dcm3", "--out", str(tmp_path / "r"))
    assert code != 0 and "holonet-dcm3" in err and len(err.strip().splitlines()) == 1
    code, _, err = _run(capsys, "bench", "reproduce", "--resume", str(tmp_path / "nothing"))
    assert code == 2 and "no plan.json" in err


def test_the_recorded_reproduction_command_names_every_setting_and_only_a_given_profile() -> None:
    settings = dict(size=(136, 240), methods=["ccnn", "ccnn-dcm4"], seeds=[42, 43], ablation_seeds=None, colour="red",
                    data="procedural:2", lr=5e-4, max_steps=8192, min_steps=1024, min_gain_db=0.2, patience=2,
                    iris_test=True,
                    jobs=2, threads=1)
    default = reproduce_command(None, Path("out dir"), **settings)
    assert default == ("benchctl bench reproduce --size 136x240 --methods ccnn,ccnn-dcm4 --seeds 42,43 --colour red "
                       "--data procedural:2 --lr 0.0005 --max-steps 8192 --min-steps 1024 --min-gain 0.2 --patience 2 "
                       "--jobs 2 "
                       "--threads 1 --out 'out dir'")
    named = reproduce_command("simulated", Path("o"), **settings | {"iris_test": False, "ablation_seeds": [7]})
    assert named.startswith("benchctl bench reproduce --profile simulated --size 136x240 ")
    assert "--ablation-seeds 7 " in named and "--no-iris-test" in named


def _curve(values: dict[int, float]) -> list[Evaluation]:
    return [Evaluation(step, 0.0, 0.0, val, 0.0, 0.0) for step, val in values.items()]


def test_one_dip_of_a_noisy_curve_does_not_end_a_job_two_flat_doublings_do() -> None:
    """ccnn-dcm4 (seed 42, 136 x 240) dipped at step 1024 after rising 1.3 dB over its last doubling: with patience 1
    that ended it; the rule asks for `patience` power-of-two evaluations in a row that each gained < min_gain."""
    rising = {256: 23.38, 362: 23.94, 512: 24.57, 724: 24.49, 1024: 23.98}
    curve = _curve(rising)
    assert doubling_gain(curve) == pytest.approx(-0.02, abs=1e-9)
    assert flat_doublings(curve, 1024, 0.2) == 1  # a stop under patience 1, not under 2
    flat = _curve(rising | {1448: 24.1, 2048: 24.2})
    assert doubling_gain(flat) == pytest.approx((24.2 + 24.1 - 23.98 - 24.49) / 2)
    assert flat_doublings(flat, 1024, 0.2) == 2
    assert flat_doublings(_curve(rising | {1448: 25.0, 2048: 25.4}), 1024, 0.2) == 0  # rising again
    assert flat_doublings(flat, 2048, 0.2) == 1  # evaluations before min_steps do not count


def test_a_report_of_a_folder_without_a_readable_plan_is_one_line(capsys, tmp_path: Path) -> None:
    code, _, err = _run(capsys, "bench", "reproduce", "--report", str(tmp_path / "none"))
    assert code != 0 and err.strip() == (f"benchctl: error: {tmp_path / 'none'}: not a reproduction run (no "
                                         f"plan.json); start one with --out {tmp_path / 'none'}")
    for text, reason in (("{", "Expecting property name"), ("[1, 2]", "a JSON object is expected")):
        (tmp_path / "plan.json").write_text(text)
        code, _, err = _run(capsys, "bench", "reproduce", "--report", str(tmp_path))
        assert code != 0 and "Traceback" not in err and len(err.strip().splitlines()) == 1
        assert err.startswith(f"benchctl: error: {tmp_path / 'plan.json'}: not a readable plan (") and reason in err
