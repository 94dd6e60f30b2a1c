"""The learning-rate schedule of `benchctl train` and `bench reproduce`: a linear warm-up, then constant or a
cosine decay to zero at the last step.

The rate depends on the step alone, so a resumed run continues on the same schedule. Warm-up exists because the
pyramid's stacked networks can clamp their whole output at +-pi in their first steps at the paper's rate and never
recover (docs/reproduction.md); decay because a constant rate with batch 1 leaves a curve that dips by several dB
between evaluations, so a network's end score depends on where the last step falls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from benchctl.errors import BadValueError

DECAYS = ("none", "cosine")


@dataclass(frozen=True)
class Schedule:
    """`lr` after a linear warm-up over `warmup` steps, then constant (`decay` none) or cosine down to zero at
    step `total`."""

    lr: float
    warmup: int = 0
    decay: str = "none"
    total: int | None = None

    def __post_init__(self) -> None:
        if self.decay not in DECAYS:
            raise BadValueError(f"--decay {self.decay!r}: expected one of {', '.join(DECAYS)}")
        if self.warmup < 0:
            raise BadValueError(f"--warmup must be >= 0 steps, got {self.warmup}")
        if self.decay != "none" and self.total is None:
            raise BadValueError(f"--decay {self.decay} needs a last step (--max-steps or --epochs)")
        if self.total is not None and self.warmup >= self.total:
            raise BadValueError(f"--warmup {self.warmup} must be shorter than the run ({self.total} steps)")

    def at(self, step: int) -> float:
        """The rate of step `step` (0 for the first step)."""
        if step < self.warmup:
            return self.lr * (step + 1) / self.warmup
        if self.decay == "cosine":
            assert self.total is not None
            progress = min(1.0, (step - self.warmup) / max(1, self.total - self.warmup))
            return self.lr * 0.5 * (1 + math.cos(math.pi * progress))
        return self.lr

    def apply(self, optimiser: torch.optim.Optimizer, step: int) -> None:
        """Set every parameter group of `optimiser` to the rate of step `step`."""
        rate = self.at(step)
        for group in optimiser.param_groups:
            group["lr"] = rate

    def describe(self) -> str:
        """In words, for logs and reports: 'lr 0.0005, 256 warm-up steps, cosine decay to step 32768'."""
        parts = [f"lr {self.lr:g}"]
        if self.warmup:
            parts.append(f"{self.warmup} warm-up steps")
        if self.decay != "none":
            parts.append(f"{self.decay} decay to step {self.total}")
        return ", ".join(parts)
