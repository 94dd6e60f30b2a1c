"""`bench reproduce --slurm` against a real one-node SLURM cluster (Debian's slurmctld, slurmd and munge, set up
by .ci/slurm-up): the same curves as the local pool bit for bit, a job killed on its node resumes from its
state, and a wrong partition or a missing SLURM is one line."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from benchctl.benchmarks import reproduce_slurm
from benchctl.benchmarks.reproduce import new_plan, run_reproduction
from benchctl.benchmarks.reproduce_job import read_done, read_progress, run_job
from benchctl.cli import main
from benchctl.errors import BenchctlError
from benchctl.profiles import load_profile

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = dict(size=(32, 48), methods=["ccnn", "ccnn-dcm4"], seeds=[1], data="procedural:2", max_steps=256,
                min_steps=256, first_evaluation=2, iris_test=False)


@pytest.fixture(scope="session")
def slurm_partition() -> str:
    """The one-node cluster's default partition, started by .ci/slurm-up where it is not running (root)."""
    proc = subprocess.run(["bash", str(ROOT / ".ci" / "slurm-up")], capture_output=True, text=True, timeout=120)
    if proc.returncode != 0:
        pytest.fail(f"no SLURM cluster for the tests (.ci/slurm-up): {proc.stderr.strip()}")
    return "debug"


def _timeless(curve: list[dict]) -> list[dict]:
    return [e | {"cpu_seconds": 0, "wall_seconds": 0, "gpu_seconds": None} for e in curve]


def _kill_task(array_task: str) -> None:
    """SIGKILL the training process of SLURM job `array_task` on this node, as the out-of-memory killer or a lost
    node would. (scancel is no use for this: it sends SIGTERM, which submitit lets pass, and the small job
    finishes within KillWait before SIGKILL comes.)"""
    job_id = subprocess.run(["squeue", "--noheader", "--jobs", array_task, "--format", "%A"], capture_output=True,
                            text=True, check=True).stdout.strip()
    listed = subprocess.run(["scontrol", "listpids", job_id], capture_output=True, text=True, check=True).stdout
    pids = [int(row.split()[0]) for row in listed.splitlines()[1:] if row.split()[2:3] == ["0"]]
    assert pids, listed
    for pid in pids:
        os.kill(pid, signal.SIGKILL)


@pytest.mark.slow  # two small jobs locally and on the cluster, one of them twice: about a minute unloaded
def test_a_plan_on_slurm_gives_the_local_curves_bit_for_bit_and_a_killed_job_resumes(
        slurm_partition: str, tmp_path: Path, small_profile_path: Path) -> None:
    profile = load_profile(str(small_profile_path))
    local, cluster = tmp_path / "local", tmp_path / "cluster"
    new_plan(local, profile, **SETTINGS)
    expected = {name: run_job(local, name, out=lambda _: None) for name in ("ccnn-s1", "ccnn-dcm4-s1")}
    new_plan(cluster, profile, slurm={"partition": slurm_partition, "time_min": 10}, **SETTINGS)
    lines: list[str] = []
    run_reproduction(cluster, memory=False, out=lines.append)  # submits the array and returns
    assert lines[1].startswith(f"submitted 2 job(s) to SLURM partition {slurm_partition} as array ")
    first = json.loads((cluster / "slurm.json").read_text())["submissions"][0]["jobs"]["ccnn-s1"]
    deadline = time.monotonic() + 300
    while len(read_progress(cluster, "ccnn-s1")) < 2:  # two evaluations saved: then kill it mid-way
        assert time.monotonic() < deadline and read_done(cluster, "ccnn-s1") is None, "ccnn-s1 never got going"
        time.sleep(0.02)
    _kill_task(first)
    while reproduce_slurm.queued([first]):
        time.sleep(0.5)
    assert read_done(cluster, "ccnn-s1") is None  # it was stopped before its end
    killed_at = len(read_progress(cluster, "ccnn-s1"))
    lines.clear()
    run_reproduction(cluster, memory=False, wait=True, out=lines.append)  # --resume --wait: submits it again
    assert any("to submit (ccnn-s1)" in line for line in lines), lines
    log = next((cluster / "slurm").glob("*/*_log.out"), None)
    assert log is not None
    for name, done in expected.items():
        got = read_done(cluster, name)
        assert got is not None and got["reason"] == done["reason"] == "step cap"
        assert _timeless(got["curve"]) == _timeless(done["curve"])  # bit for bit: floats compared exactly
        assert got["per_image"] == done["per_image"]
    resumed_logs = "".join(p.read_text() for p in (cluster / "slurm").glob("*/*_log.out"))
    assert "ccnn-s1: resuming at step" in resumed_logs and killed_at < len(expected["ccnn-s1"]["curve"])
    submissions = json.loads((cluster / "slurm.json").read_text())["submissions"]
    assert [sorted(s["jobs"]) for s in submissions] == [["ccnn-dcm4-s1", "ccnn-s1"], ["ccnn-s1"]]
    assert (cluster / "reproduction.md").is_file()


def test_a_wrong_partition_or_no_slurm_is_one_line(slurm_partition: str, capsys, tmp_path: Path,
                                                  small_profile_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    code = main(["bench", "reproduce", "--profile", str(small_profile_path), "--methods", "ccnn", "--slurm",
                 "nosuchpartition", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "--slurm nosuchpartition: no such partition on this cluster (there are: debug*, other" in err
    assert not (tmp_path / "r").exists()
    monkeypatch.setenv("PATH", str(tmp_path))  # no sbatch, no sinfo
    with pytest.raises(BenchctlError, match="SLURM's commands .* are not on this machine's PATH"):
        new_plan(tmp_path / "r", load_profile(str(small_profile_path)), methods=["ccnn"],
                 slurm={"partition": "debug", "time_min": 5})
