"""The paper's ablation variants in use (train, checkpoint, generate), combined training data, and the
`bench reproduce` command end to end on a tiny grid."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from benchctl.benchmarks.reproduce import DEFAULT_METHODS, PAPER, reproduce_command
from benchctl.cli import main
from benchctl.errors import BadValueError
from benchctl.runner.learned.checkpoint import read_checkpoint
from benchctl.runner.learned.data import image_sources
from benchctl.targets import photo_specs

ABLATIONS = ("holonet-ps2", "holonet-ps4", "holonet-lowdef2", "holonet-dcm2-nolfm", "holonet-dcm2-noeccm",
             "holonet-dcm2-nogrn")


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


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


def test_reproduce_runs_end_to_end_and_writes_table_curves_and_plots(capsys, tmp_path: Path,
                                                                     small_profile_path: Path) -> None:
    out = tmp_path / "repro"
    code, stdout, err = _run(capsys, "bench", "reproduce", "--profile", str(small_profile_path), "--size", "32x48",
                             "--steps", "2", "--methods", "holonet-ps2,ccnn", "--data", "procedural:2",
                             "--evaluations", "2", "--out", str(out))
    assert code == 0, err
    rows = list(csv.DictReader((out / "reproduction.csv").open()))
    assert [r["method"] for r in rows] == ["holonet-ps2", "ccnn"]
    for row in rows:
        assert int(row["steps"]) == 2 and int(row["equal_steps"]) == 2
        assert 0 < float(row["time_psnr_db"]) < 60 and 0 < float(row["time_ssim"]) <= 1
        assert float(row["paper_psnr_db"]) == PAPER[row["method"]][0]
        assert float(row["train_step_peak_mib"]) > 0 and float(row["inference_seconds"]) > 0
    assert rows[1]["baseline"] == "ccnn" and float(rows[1]["time_delta_db"]) == 0.0
    assert rows[0]["baseline"] == ""  # holonet, its baseline, was not run
    curves = list(csv.DictReader((out / "curves.csv").open()))
    assert [(c["method"], int(c["step"])) for c in curves] == [("holonet-ps2", 1), ("holonet-ps2", 2), ("ccnn", 1),
                                                               ("ccnn", 2)]
    report = (out / "reproduction.md").read_text()
    assert "| method | paper PSNR / SSIM |" in report and "| dpac (classical reference) |" in report
    assert "benchctl bench reproduce" in report
    for name in ("psnr_vs_step.png", "psnr_vs_seconds.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "DPAC on the held-out photographs" in stdout


def test_reproduce_user_mistakes_are_one_line_errors(capsys, small_profile_path: Path) -> None:
    assert set(DEFAULT_METHODS) <= set(PAPER)
    code, _, err = _run(capsys, "bench", "reproduce", "--profile", str(small_profile_path), "--steps", "1",
                        "--methods", "holonet-dcm3")
    assert code != 0 and "holonet-dcm3" in err and len(err.strip().splitlines()) == 1


def test_the_recorded_reproduction_command_names_every_setting_and_only_a_given_profile() -> None:
    default = reproduce_command(None, (136, 240), 0.5, None, ["ccnn", "ccnn-dcm4"], "red", "procedural:2", 5, 1e-3,
                                42, 1, Path("out dir"))
    assert default == ("benchctl bench reproduce --size 136x240 --minutes 0.5 --methods ccnn,ccnn-dcm4 --colour red "
                       "--data procedural:2 --evaluations 5 --lr 0.001 --seed 42 --threads 1 --out 'out dir'")
    named = reproduce_command("simulated", (136, 240), None, 3, ["ccnn"], "red", "procedural:2", 1, 1e-3, 0, None,
                              None)
    assert named.startswith("benchctl bench reproduce --profile simulated --size 136x240 --steps 3 ")
