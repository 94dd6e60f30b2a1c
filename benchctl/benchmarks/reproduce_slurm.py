"""`bench reproduce --slurm PARTITION`: the plan's unfinished jobs as one SLURM job array, through submitit.

submitit (Meta's maintained SLURM client) writes the sbatch script, submits the array, and turns SLURM's warning
signal before a time-out or a preemption into a requeue of the same call; each task runs `run_job`, which
continues from the job's saved state (the exact resume of `reproduce_job`), so a requeued, preempted or
cancelled-and-resubmitted task ends with the curve an uninterrupted one gives. The run folder must be on a file
system the nodes share. `--resume DIR` collects: finished jobs are kept, jobs still in SLURM's queue are left
to run, and jobs that left the queue unfinished (cancelled, failed, node lost) are submitted again.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from benchctl.benchmarks.reproduce_job import JOB_DEVICE_ENV, read_done, run_job
from benchctl.errors import BadValueError, BenchctlError
from benchctl.files import write_json
from benchctl.training.device import VISIBLE_ENV

SLURM_FILE = "slurm.json"
MAX_SUBMISSIONS = 3  # a job that left the queue unfinished this often fails by itself: its log says why
QUEUED = ("PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "REQUEUED", "RESIZING", "SUSPENDED", "REQUEUE_HOLD",
          "REQUEUE_FED", "SIGNALING", "STAGE_OUT")


class SlurmTask:
    """One array task: train one job of the plan (resuming its state). On a time-out or preemption submitit calls
    `checkpoint`, which resubmits the same call; the job then continues from its last saved state."""

    def __call__(self, run_dir: str, name: str) -> str:
        run_job(Path(run_dir), name, out=lambda line: print(line, flush=True))
        return name

    def checkpoint(self, run_dir: str, name: str) -> Any:
        import submitit

        return submitit.helpers.DelayedSubmission(self, run_dir, name)


def _submitit() -> Any:
    try:
        import submitit
    except ImportError:
        raise BenchctlError("--slurm needs submitit: pip install 'benchctl[cluster]'") from None
    return submitit


def partitions() -> list[str]:
    """The cluster's partitions (the default one first, as sinfo marks it); one line where SLURM is not here."""
    if shutil.which("sinfo") is None or shutil.which("sbatch") is None:
        raise BenchctlError("--slurm: SLURM's commands (sbatch, sinfo) are not on this machine's PATH; run "
                            "without --slurm for the local pool, or on the cluster's login node")
    proc = subprocess.run(["sinfo", "--noheader", "--format=%P"], capture_output=True, text=True, check=False,
                          timeout=60)
    if proc.returncode != 0:
        raise BenchctlError(f"--slurm: sinfo failed ({(proc.stderr or proc.stdout).strip().splitlines()[-1:]}): is "
                            "the SLURM controller reachable from here?")
    names = [p.strip() for p in proc.stdout.split()]
    return sorted(names, key=lambda p: not p.endswith("*"))


def check_partition(partition: str) -> None:
    """One line naming the partitions there are when `partition` is not one of them."""
    known = partitions()
    if partition not in [p.rstrip("*") for p in known]:
        raise BadValueError(f"--slurm {partition}: no such partition on this cluster (there are: "
                            f"{', '.join(known)}; * marks the default)")


def submit(run_dir: Path, plan: dict[str, Any], names: Sequence[str], out: Callable[[str], None] = print) -> list[str]:
    """Submit `names` (jobs of the plan in `run_dir`) as one job array with the plan's SLURM settings; their
    SLURM job ids, also recorded in `run_dir/slurm.json`."""
    settings = plan["slurm"]
    check_partition(settings["partition"])
    submitit = _submitit()
    gpu = plan.get("device", "cpu") != "cpu"
    executor = submitit.AutoExecutor(folder=Path(run_dir) / "slurm" / "%j", cluster="slurm")
    threads = str(plan["threads"])
    executor.update_parameters(
        name=f"reproduce-{Path(run_dir).name}", slurm_partition=settings["partition"],
        timeout_min=settings["time_min"], cpus_per_task=plan["threads"], tasks_per_node=1, nodes=1,
        slurm_array_parallelism=settings.get("parallel", 256),
        slurm_gpus_per_task=1 if gpu else None,
        slurm_setup=[f"export OMP_NUM_THREADS={threads} MKL_NUM_THREADS={threads}",
                     f"export {JOB_DEVICE_ENV}={'cuda:0' if gpu else 'cpu'}"]
        + ([] if gpu else [f"export {VISIBLE_ENV}="]))
    try:
        jobs = executor.map_array(SlurmTask(), [str(run_dir)] * len(names), list(names))
    except Exception as exc:  # submitit raises sbatch's own refusal; keep its last line
        last = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise BenchctlError(f"--slurm {settings['partition']}: sbatch refused the job array: {last}") from None
    ids = [job.job_id for job in jobs]
    record = read_record(run_dir)
    record.setdefault("submissions", []).append({"time": time.strftime("%Y-%m-%d %H:%M:%S"),
                                                 "jobs": dict(zip(names, ids))})
    write_json(Path(run_dir) / SLURM_FILE, record)
    out(f"submitted {len(ids)} job(s) to SLURM partition {settings['partition']} as array {ids[0].split('_')[0]} "
        f"(logs in {Path(run_dir) / 'slurm'}); collect with: benchctl bench reproduce --resume {run_dir}")
    return ids


def read_record(run_dir: Path) -> dict[str, Any]:
    """What was submitted: slurm.json's list of submissions, each naming job -> SLURM job id."""
    path = Path(run_dir) / SLURM_FILE
    return json.loads(path.read_text()) if path.is_file() else {}


def queued(ids: Sequence[str]) -> dict[str, str]:
    """SLURM job id -> state, for the ids still in SLURM's queue (pending, running, requeued ...)."""
    if not ids:
        return {}
    proc = subprocess.run(["squeue", "--noheader", "--array", "--format=%i %T", "--jobs", ",".join(ids)],
                          capture_output=True, text=True, check=False, timeout=60)
    states = {}
    for line in proc.stdout.splitlines():
        job, _, state = line.strip().partition(" ")
        if state in QUEUED:
            states[job] = state
    return states


def collect(run_dir: Path, plan: dict[str, Any], out: Callable[[str], None] = print, *,
            wait: bool = False, poll_s: float = 5.0) -> list[str]:
    """Where a SLURM run stands: submit again every unfinished job that left the queue (up to MAX_SUBMISSIONS
    times); with `wait`, until no job is left in the queue. The names of the jobs still unfinished."""
    while True:
        unfinished = [j["name"] for j in plan["jobs"] if read_done(run_dir, j["name"]) is None]
        submissions = read_record(run_dir).get("submissions", [])
        latest = {name: job for s in submissions for name, job in s["jobs"].items()}
        tries = {name: sum(name in s["jobs"] for s in submissions) for name in unfinished}
        states = queued([latest[n] for n in unfinished if n in latest])
        waiting = [n for n in unfinished if latest.get(n) in states]
        failed = [n for n in unfinished if n not in waiting and tries[n] >= MAX_SUBMISSIONS]
        lost = [n for n in unfinished if n not in waiting and n not in failed]
        done = len(plan["jobs"]) - len(unfinished)
        out(f"SLURM: {done} of {len(plan['jobs'])} jobs finished, {len(waiting)} in the queue"
            + (f", {len(lost)} to submit ({', '.join(lost)})" if lost else "")
            + (f", {len(failed)} failed {MAX_SUBMISSIONS} times ({', '.join(failed)}: see their logs in "
               f"{Path(run_dir) / 'slurm'})" if failed else ""))
        if lost:
            submit(run_dir, plan, lost, out)
            waiting += lost
        if not waiting or not wait:
            return waiting + failed
        time.sleep(poll_s)
