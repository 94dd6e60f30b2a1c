"""`benchctl train` under DistributedDataParallel: two CPU processes, gloo, the environment torchrun sets."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp
from conftest import SMALL_PROFILE

from benchctl.calibration.setups import optical_setup
from benchctl.cgh.learned import build_model
from benchctl.holograms.checkpoints import read_checkpoint
from benchctl.profiles import load_profile
from benchctl.training.training import TrainSettings, train

pytestmark = pytest.mark.slow  # DDP spawns: seconds to a minute each

SETTINGS = TrainSettings(method="holonet-dcm2", data="procedural:5", epochs=1, lr=1e-3, val_fraction=0.2)


def _worker(rank: int, world_size: int, port: int, folder: str) -> None:
    """One torchrun-like process: the environment torchrun would set, then the same call `benchctl train` makes."""
    os.environ.update(RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE=str(world_size), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port))
    torch.set_num_threads(1)
    root = Path(folder)
    result = train(load_profile(root / "small.toml"), SETTINGS, root / "out", {"red": 0, "green": 1, "blue": 2},
                   out=lambda line: (root / f"stdout-{rank}.txt").open("a").write(line + "\n"))
    assert result.rank == rank and result.world_size == world_size
    torch.save({"steps": result.steps, "checkpoint": str(result.checkpoint),
                "parameters": {c: dict(m.named_parameters()) for c, m in result.models.items()}},
               root / f"rank{rank}.pt")


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_two_process_gloo_training_keeps_ranks_identical_and_rank_zero_writes(tmp_path: Path) -> None:
    (tmp_path / "small.toml").write_text(SMALL_PROFILE)
    mp.start_processes(_worker, args=(2, _free_port(), str(tmp_path)), nprocs=2, start_method="spawn")
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(2)]
    # 4 training images, 2 processes x batch 1: 2 steps, each on both processes.
    assert ranks[0]["steps"] == ranks[1]["steps"] == 2
    assert ranks[1]["checkpoint"] == "None" and ranks[0]["checkpoint"] == str(tmp_path / "out" / "holonet-dcm2.pt")
    assert not (tmp_path / "stdout-1.txt").exists() and "epoch 1/1" in (tmp_path / "stdout-0.txt").read_text()
    checkpoint = read_checkpoint(tmp_path / "out" / "holonet-dcm2.pt")
    assert checkpoint.training["processes"] == 2 and checkpoint.training["steps"] == 2
    profile = load_profile(tmp_path / "small.toml")
    for colour in ("red", "green", "blue"):
        torch.manual_seed(SETTINGS.seed)  # the weights every process started from
        initial = dict(build_model(SETTINGS.method, optical_setup(profile, colour)).named_parameters())
        params0, params1 = ranks[0]["parameters"][colour], ranks[1]["parameters"][colour]
        assert params0.keys() == params1.keys() == initial.keys()
        for name, value in params0.items():
            assert torch.equal(value, params1[name]), (colour, name)  # all-reduced gradients: identical weights
            assert torch.equal(checkpoint.weights[colour][name], value), (colour, name)
        assert sum(not torch.equal(v, initial[k]) for k, v in params0.items()) > len(initial) // 2  # it trained
