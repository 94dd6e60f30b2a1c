"""Where training runs (`--device auto|cpu|cuda[:N]`) and how its time is measured there.

A job of `bench reproduce` is pinned to one GPU by CUDA_VISIBLE_DEVICES (its pool sets it per subprocess), so
inside a job that GPU is cuda:0. The clock of the stopping rule and the equal-time comparison is CPU time on CPU
(independent of the machine's other load) and, on a GPU, wall time with the device synchronised before each
reading (CPU time there is the host's launching, not the work).
"""

from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass, field

import torch

from benchctl.errors import BadValueError

DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(?::(\d+))?")
VISIBLE_ENV = "CUDA_VISIBLE_DEVICES"


def check_device_text(text: str) -> str:
    """`text` if it names a device benchctl trains on (auto, cpu, cuda, cuda:N); one line naming it otherwise."""
    if DEVICE_PATTERN.fullmatch(text) is None:
        raise BadValueError(f"--device {text!r}: expected auto, cpu, cuda or cuda:N (e.g. cuda:1)")
    return text


def cuda_count() -> int:
    """The CUDA devices torch can use here (0 without a driver, a GPU or a CUDA build of torch)."""
    return torch.cuda.device_count() if torch.cuda.is_available() else 0


def resolve_device(text: str, local_rank: int = 0) -> torch.device:
    """The torch device `--device text` names on this machine: auto is a GPU where there is one, else the CPU;
    auto and cuda mean GPU `local_rank` (modulo the GPUs here: torchrun's processes one per GPU). A GPU that is
    not here is one line that says what is (never a CUDA traceback later)."""
    match = DEVICE_PATTERN.fullmatch(check_device_text(text))
    assert match is not None
    count = cuda_count()
    if text == "auto" or text == "cuda" and count:
        return torch.device("cuda", local_rank % count) if count else torch.device("cpu")
    if text == "cpu":
        return torch.device("cpu")
    if count == 0:
        build = f"torch {torch.__version__} has no CUDA support" if torch.version.cuda is None else \
            f"torch {torch.__version__} (CUDA {torch.version.cuda}) finds no GPU"
        visible = os.environ.get(VISIBLE_ENV)
        raise BadValueError(f"--device {text}: no CUDA device on this machine ({build}"
                            + (f"; {VISIBLE_ENV}={visible!r}" if visible is not None else "")
                            + "): use --device cpu or auto")
    index = int(match[1] or 0)
    if index >= count:
        raise BadValueError(f"--device {text}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return torch.device("cuda", index)


def gpu_slots(device_text: str, jobs_per_gpu: int) -> list[str | None]:
    """What each concurrent job of a pool sees as CUDA_VISIBLE_DEVICES: `jobs_per_gpu` slots per GPU that
    `device_text` allows (auto and cuda: every GPU here; cuda:N: that one), None per slot on CPU (no pinning).
    The number of slots is the pool's largest number of jobs at a time on GPUs."""
    device = resolve_device(device_text)
    if device.type == "cpu":
        return [None]
    visible = os.environ.get(VISIBLE_ENV)
    names = [v.strip() for v in visible.split(",")] if visible else [str(i) for i in range(cuda_count())]
    gpus = names if device_text in ("auto", "cuda") else [names[device.index or 0]]
    return [gpu for gpu in gpus for _ in range(jobs_per_gpu)]


@dataclass
class StepClock:
    """Seconds spent in training steps: CPU time of this process, wall time, and on a GPU wall time with the
    device synchronised at both ends of each step (`gpu`), the clock a GPU run is stopped and compared by."""

    device: torch.device
    cpu: float = 0.0
    wall: float = 0.0
    gpu: float = 0.0
    _start: tuple[float, float] = field(default=(0.0, 0.0), repr=False)

    def start(self) -> None:
        self._sync()
        self._start = (time.perf_counter(), time.process_time())

    def stop(self) -> None:
        self._sync()
        wall = time.perf_counter() - self._start[0]
        self.wall += wall
        self.cpu += time.process_time() - self._start[1]
        if self.device.type == "cuda":
            self.gpu += wall

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
