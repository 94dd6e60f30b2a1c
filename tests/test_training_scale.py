"""Training at lab scale: the learning-rate schedule, the device plumbing (--device, GPUs per job), the held-out
set of `bench reproduce`, and the resume of a job stopped after its last state and before its record."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import pytest
import torch

from benchctl.benchmarks import reproduce, reproduce_job
from benchctl.benchmarks.reproduce import new_plan, run_jobs
from benchctl.benchmarks.reproduce_job import run_job
from benchctl.benchmarks.reproduce_report import t975, t_interval, verdict, write_report
from benchctl.cli import main
from benchctl.errors import BadValueError
from benchctl.profiles import load_profile
from benchctl.training import device as device_module
from benchctl.training.data import image_sources
from benchctl.training.device import gpu_slots, resolve_device
from benchctl.training.schedule import Schedule
from benchctl.training.training import Distributed


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    try:
        code = main(list(argv))
    except SystemExit as exc:  # argparse's refusal of an argument's value
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_warm_up_rises_linearly_and_cosine_decay_reaches_zero_at_the_last_step() -> None:
    schedule = Schedule(1e-3, warmup=4, decay="cosine", total=14)
    rates = [schedule.at(step) for step in range(15)]
    assert rates[:4] == pytest.approx([2.5e-4, 5e-4, 7.5e-4, 1e-3])
    assert rates[4] == pytest.approx(1e-3) and rates[9] == pytest.approx(5e-4)  # half-way through the decay
    assert rates[14] == pytest.approx(0.0, abs=1e-12) and all(a >= b for a, b in zip(rates[4:], rates[5:]))
    assert Schedule(1e-3).at(0) == Schedule(1e-3).at(10**6) == 1e-3
    optimiser = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    schedule.apply(optimiser, 1)
    assert optimiser.param_groups[0]["lr"] == pytest.approx(5e-4)
    for kwargs, match in (({"decay": "linear"}, "--decay"), ({"warmup": -1}, "--warmup"),
                          ({"decay": "cosine"}, "needs a last step"), ({"warmup": 10, "total": 10}, "shorter")):
        with pytest.raises(BadValueError, match=match):
            Schedule(1e-3, **kwargs)


def test_a_cuda_device_on_a_machine_without_one_is_one_line(capsys, monkeypatch: pytest.MonkeyPatch,
                                                            small_profile_path: Path, tmp_path: Path) -> None:
    monkeypatch.setattr(device_module, "cuda_count", lambda: 0)
    assert resolve_device("auto") == torch.device("cpu") and resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(BadValueError, match=r"--device cuda:1: no CUDA device on this machine"):
        resolve_device("cuda:1")
    for argv in (["train", "--method", "ccnn", "--data", "procedural:2", "--profile", str(small_profile_path),
                  "--device", "cuda", "--out", str(tmp_path / "t")],
                 ["bench", "reproduce", "--profile", str(small_profile_path), "--methods", "ccnn", "--device", "cuda",
                  "--out", str(tmp_path / "r")]):
        code, _, err = _run(capsys, *argv)
        assert code == 2 and len(err.strip().splitlines()) == 1 and "no CUDA device on this machine" in err, err
    assert not (tmp_path / "t").exists() and not (tmp_path / "r").exists()
    code, _, err = _run(capsys, "train", "--method", "ccnn", "--data", "procedural:2", "--device", "gpu0")
    assert code == 2 and "expected auto, cpu, cuda or cuda:N" in err
    monkeypatch.setattr(device_module, "cuda_count", lambda: 2)
    with pytest.raises(BadValueError, match=r"2 CUDA device\(s\), cuda:0 to cuda:1"):
        resolve_device("cuda:2")


def test_each_job_is_pinned_to_one_gpu_k_jobs_per_gpu(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                      small_profile_path: Path) -> None:
    monkeypatch.setattr(device_module, "cuda_count", lambda: 2)
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert gpu_slots("cuda", 2) == ["0", "0", "1", "1"] and gpu_slots("cuda:1", 1) == ["1"]
    assert gpu_slots("cpu", 3) == [None]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,5")  # a pool inside a scheduler's allocation keeps its GPUs
    assert gpu_slots("auto", 1) == ["3", "5"] and gpu_slots("cuda:1", 2) == ["5", "5"]
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")

    new_plan(tmp_path, load_profile(str(small_profile_path)), size=(32, 48), methods=["ccnn", "ccnn-dcm4"],
             seeds=[1, 2], data="procedural:2", max_steps=4, min_steps=2, first_evaluation=2, iris_test=False,
             device="cuda")
    started: list[tuple[str, str, str, int]] = []
    live: set[str] = set()

    class FakeJob:  # a job process that finishes after two polls, writing its record
        def __init__(self, argv: list[str], env: dict[str, str], **_: Any) -> None:
            self.name, self.polls, self.returncode = argv[-1], 0, None
            gpu = env["CUDA_VISIBLE_DEVICES"]
            started.append((self.name, gpu, env["BENCHCTL_JOB_DEVICE"], len(live)))
            live.add(gpu)

        def poll(self) -> int | None:
            self.polls += 1
            if self.polls < 2:
                return None
            (tmp_path / "jobs" / self.name / "done.json").write_text(json.dumps(
                {"reason": "step cap", "steps": 4, "cpu_seconds": 1.0, "gpu_seconds": 0.5, "curve": []}))
            live.discard(next(g for n, g, _, _ in started if n == self.name))
            self.returncode = 0
            return 0

    monkeypatch.setattr(reproduce.subprocess, "Popen", FakeJob)
    monkeypatch.setattr(reproduce, "POLL_S", 0.0)
    lines: list[str] = []
    assert run_jobs(tmp_path, jobs=8, out=lines.append, jobs_per_gpu=1) == []
    assert [(name, gpu, device) for name, gpu, device, _ in started[:2]] == \
        [("ccnn-s1", "0", "cuda:0"), ("ccnn-dcm4-s1", "1", "cuda:0")]
    assert len(started) == 4 and all(busy < 2 for *_, busy in started)  # never two jobs on one GPU
    assert "2 at a time, 1 per GPU on GPU(s) 0, 1" in lines[0] and "(0.0 GPU-min)" in lines[-1]


def test_torchrun_processes_take_the_gpu_of_their_local_rank(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(device_module, "cuda_count", lambda: 2)
    monkeypatch.setenv("LOCAL_RANK", "3")
    monkeypatch.setenv("WORLD_SIZE", "1")
    assert Distributed.from_env("cuda").device == torch.device("cuda", 1)
    assert Distributed.from_env("cuda:0").device == torch.device("cuda", 0)
    assert Distributed.from_env("cpu").device == torch.device("cpu")
    monkeypatch.setenv("BENCHCTL_JOB_DEVICE", "cpu")  # a pool's pinning wins over the plan's --device
    assert reproduce_job.job_device({"device": "cuda"}) == torch.device("cpu")


def test_seed_and_methods_mistakes_are_refused_in_one_line(capsys, small_profile_path: Path, tmp_path: Path) -> None:
    code, _, err = _run(capsys, "train", "--method", "ccnn", "--data", "procedural:2", "--profile",
                        str(small_profile_path), "--seed", "-1", "--out", str(tmp_path / "t"))
    assert code == 2 and "--seed: must lie between 0 and 4294967295, got -1" in err  # was a numpy traceback
    code, _, err = _run(capsys, "bench", "reproduce", "--profile", str(small_profile_path), "--methods", "",
                        "--out", str(tmp_path / "r"))
    assert code == 2 and "--methods: give at least one learned method" in err  # was: all 12 jobs, silently
    assert not (tmp_path / "r").exists()


def test_a_held_out_range_of_procedural_images_and_its_mistakes() -> None:
    assert [s.index for s in image_sources("procedural:200000-200002")] == [200000, 200001, 200002]
    assert [s.index for s in image_sources("procedural:3")] == [0, 1, 2]
    for bad in ("procedural:0", "procedural:5-3", "procedural:3-", "procedural:-3", "procedural:1-1000001"):
        with pytest.raises(BadValueError, match="procedural:A-B"):
            image_sources(bad)


@pytest.mark.slow
def test_a_job_stopped_between_its_last_state_and_its_record_ends_without_training(
        tmp_path: Path, small_profile_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    new_plan(tmp_path, load_profile(str(small_profile_path)), size=(32, 48), methods=["ccnn"], seeds=[1],
             data="procedural:2", max_steps=4, min_steps=2, first_evaluation=2, iris_test=False, warmup=1,
             decay="cosine", held_out="photos:eval+procedural:200000-200001")

    def stopped(*args: object, **kwargs: object) -> float:
        raise KeyboardInterrupt  # after the state at the cap was written, before done.json

    monkeypatch.setattr(reproduce_job, "inference_seconds", stopped)
    with pytest.raises(KeyboardInterrupt):
        run_job(tmp_path, "ccnn-s1", out=lambda _: None)
    assert not (tmp_path / "jobs" / "ccnn-s1" / "done.json").exists()
    monkeypatch.setattr(reproduce_job, "inference_seconds", lambda *args, **kwargs: 0.01)
    steps = {"n": 0}

    def counted(*args: object, **kwargs: object) -> object:
        steps["n"] += 1
        if steps["n"] > 3:
            raise AssertionError("a job that had reached its cap trains again")
        return training_step(*args, **kwargs)

    training_step = reproduce_job.training_step
    monkeypatch.setattr(reproduce_job, "training_step", counted)
    lines: list[str] = []
    done = run_job(tmp_path, "ccnn-s1", out=lines.append)
    assert steps["n"] == 0 and lines == ["ccnn-s1: resuming at step 4 (it had ended: step cap)"]
    assert done["reason"] == "step cap" and done["steps"] == 4 and [e["step"] for e in done["curve"]] == [2, 3, 4]
    assert [e["image"] for e in done["per_image"]] == ["photo:astronaut", "photo:coffee", "photo:chelsea",
                                                       "photo:rocket", "procedural-200000", "procedural-200001"]
    assert all(math.isfinite(e["psnr"]) and 0 < e["ssim"] <= 1 for e in done["per_image"])
    assert done["curve"][-1]["psnr"] == pytest.approx(sum(e["psnr"] for e in done["per_image"]) / 6)


def test_verdicts_follow_the_written_rule() -> None:
    assert verdict(None, 0.4) == "not resolved"  # one seed: no interval
    assert verdict((-1.08, -1.83, -0.33), 0.36) == "disagrees"  # the paper's value outside the interval
    assert verdict((0.9, 0.33, 1.47), 0.88) == "agrees"  # inside, and the interval within +-1 dB
    assert verdict((-2.8, -19.8, 14.1), 1.47) == "not resolved"  # inside, but the interval is too wide
    assert verdict((0.1, -0.2, 0.4), -14.2, "the iris") == "not testable here"
    mean, low, high = t_interval([-1.39, -1.06, -0.78])  # t(0.975, 2 dof) = 4.3027
    assert (mean, low, high) == pytest.approx((-1.0767, -1.0767 - 4.3027 * 0.30531 / 3 ** 0.5,
                                               -1.0767 + 4.3027 * 0.30531 / 3 ** 0.5), abs=2e-4)
    assert t_interval([1.0]) is None


def test_the_t_quantiles_are_scipys() -> None:
    """The report's t quantiles (a table, then an expansion) against an implementation benchctl did not write."""
    from scipy import stats  # installed with scikit-image (the test extra)
    for dof in (*range(1, 41), 60, 100, 1000):
        assert t975(dof) == pytest.approx(float(stats.t.ppf(0.975, dof)), abs=2e-6), dof


@pytest.mark.slow  # DPAC on the four held-out photographs at 136 x 240
def test_the_shipped_reproduction_is_reported_again_from_its_csvs(tmp_path: Path) -> None:
    """docs/reproduction's run folder is gone; its CSVs hold the curves, and the report is built from them."""
    shipped = Path(__file__).resolve().parents[1] / "docs" / "reproduction"
    for name in ("plan.json", "curves.csv", "reproduction.csv"):
        (tmp_path / name).write_bytes((shipped / name).read_bytes())
    lines: list[str] = []
    rows = write_report(tmp_path, out=lines.append)
    assert {r["method"]: round(r["psnr_db"][0], 2) for r in rows}["holonet-dcm4"] == 27.02
    claims = {c["claim"]: c for c in csv.DictReader((tmp_path / "comparisons.csv").open())}
    x2 = claims["x2 about equal to HoloNet"]
    assert (round(float(x2["ci_low_db"]), 2), round(float(x2["ci_high_db"]), 2)) == (-1.83, -0.33)
    assert x2["verdict"] == "disagrees" and claims["CCNN x4 about equal to CCNN"]["verdict"] == "agrees"
    assert float(claims["SR -> PixelShuffle costs about 0.5 dB at x4"]["here_db"]) == pytest.approx(0.08, abs=0.005)
    assert claims["propagating at low definition collapses quality"]["verdict"] == "not testable here"
    assert json.loads((tmp_path / "dpac.json").read_text())["psnr_db"] == pytest.approx(27.93, abs=0.005)
    table = (tmp_path / "reproduction.md").read_text()
    assert "| holonet-dcm2 (no iris) | 1 | flat (stopping rule) | 2048 |" in table
    assert "No per-image scores: this run was reported from its CSVs" in table
    assert (tmp_path / "curves.csv").read_bytes() == (shipped / "curves.csv").read_bytes()  # its data, unchanged


@pytest.mark.slow  # the report's two plots
def test_x2_against_holonet_is_reported_again_from_its_csvs_with_its_per_image_scores(tmp_path: Path) -> None:
    """docs/reproduction/x2-vs-holonet: the converged run's jobs are gone; its CSVs rebuild the report, the
    per-image tables included, byte for byte."""
    shipped = Path(__file__).resolve().parents[1] / "docs" / "reproduction" / "x2-vs-holonet"
    for name in ("plan.json", "curves.csv", "reproduction.csv", "per_image_seeds.csv", "dpac.json"):
        (tmp_path / name).write_bytes((shipped / name).read_bytes())
    write_report(tmp_path, out=lambda _: None)
    claim = next(csv.DictReader((tmp_path / "comparisons.csv").open()))
    assert (claim["claim"], claim["seeds"], claim["per_seed_db"], claim["verdict"]) == (
        "x2 about equal to HoloNet", "42 43 44", "-0.37 -0.35 -0.53", "disagrees")
    assert [round(float(claim[k]), 2) for k in ("here_db", "ci_low_db", "ci_high_db")] == [-0.42, -0.65, -0.18]
    images = list(csv.DictReader((tmp_path / "per_image.csv").open()))
    assert len(images) == 3 * 32 and {r["seeds"] for r in images if r["method"] != "dpac"} == {"3"}
    for name in ("comparisons.csv", "per_image.csv", "reproduction.md"):
        assert (tmp_path / name).read_bytes() == (shipped / name).read_bytes(), name
