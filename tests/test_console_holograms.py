"""The console's hologram worker: a separate, lower-priority process that computes exactly what a run computes,
reports its progress, says its errors in one line and ends with the console."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from benchctl.calibration.calibrated import Calibrated
from benchctl.console.holograms import WORKER_NICE, HologramWorker, Request
from benchctl.errors import BenchctlError
from benchctl.holograms.cache import hologram
from benchctl.profiles import load_profile
from benchctl.targets import load_target, prepare_target


def request(profile_path: Path, iterations: int, method: str = "sgd") -> Request:
    profile = load_profile(profile_path)
    target = prepare_target(load_target("chart:bars", profile.optics.roi), profile.slm.shape, profile.optics.roi)
    return Request(profile, target, "green", method, iterations, 0, None)


def test_the_worker_computes_what_a_run_computes_in_its_own_process(bench_profile_path: Path) -> None:
    worker = HologramWorker()
    try:
        progress: list[tuple[str, int, int]] = []
        job = request(bench_profile_path, 4)
        result = worker.compute(job, lambda *step: progress.append(step))
        pid = worker._process.pid
        assert pid != os.getpid() and os.getpriority(os.PRIO_PROCESS, pid) == os.nice(0) + WORKER_NICE
        assert [(done, total) for _, done, total in progress][-1] == (4, 4)  # the SGD's own steps
        run = hologram(Calibrated(job.profile), job.amplitude, "green", "sgd", iterations=4, seed=0, checkpoint=None)
        assert run.cached and np.array_equal(result.gray, run.gray) and result.cached is False
        with pytest.raises(BenchctlError, match="no-such-method"):
            worker.compute(request(bench_profile_path, 4, "no-such-method"))
        assert worker.compute(job).cached is True and worker._process.pid == pid  # one process, kept
    finally:
        worker.close()
    assert worker._process is None and not Path(f"/proc/{pid}").exists()


def test_a_worker_that_dies_is_said_in_one_line_and_replaced(bench_profile_path: Path) -> None:
    worker = HologramWorker()
    started = threading.Event()
    outcome: list[Exception] = []

    def compute() -> None:
        try:
            worker.compute(request(bench_profile_path, 5000), lambda *step: started.set())
        except Exception as exc:
            outcome.append(exc)

    thread = threading.Thread(target=compute)
    thread.start()
    try:
        assert started.wait(120)
        worker._process.kill()  # out of memory, say
        thread.join(30)
        assert len(outcome) == 1 and isinstance(outcome[0], BenchctlError)
        assert "hologram worker process ended while computing" in str(outcome[0])
        assert worker.compute(request(bench_profile_path, 2)).gray.shape == (128, 192)  # a new worker
    finally:
        worker.close()


@pytest.mark.slow
def test_a_script_without_a_main_guard_can_use_the_worker(bench_profile_path: Path, tmp_path: Path) -> None:
    """The worker is a fresh `python -m` interpreter: the script that started it is not run again in it (as a
    spawned multiprocessing child would run it)."""
    script = tmp_path / "embed.py"
    script.write_text(f"""
from pathlib import Path
from benchctl.console.holograms import HologramWorker
from test_console_holograms import request
worker = HologramWorker()
print("gray", worker.compute(request(Path({str(bench_profile_path)!r}), 2)).gray.shape, flush=True)
worker.close()
""")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["gray (128, 192)"]  # once: the script ran once
