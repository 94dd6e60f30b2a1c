"""Is a network still learning? Per-step signs that training has stalled or diverged, and the verdict.

A network whose output sits at the Hardtanh's clamp (+-pi) everywhere passes no gradient back: its loss
stays where it is and every later step is wasted (the DCM pyramid does this at lr 1e-3). A loss that turns
non-finite, or rises far above the lowest it reached, has diverged. Both are told in one line, at the step
where they happened, so a training run stops with its last good state instead of training on garbage.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

CLAMP_TOLERANCE = 1e-6  # rad: an output this close to +-pi is at the clamp


@dataclass(frozen=True)
class StepStats:
    """What one training step measured: the loss, the amplitude PSNR, the gradient norm over all weights
    and the fraction of output phases at the clamp."""

    loss: float
    psnr_db: float
    grad_norm: float
    clamped: float


def clamped_fraction(phase: torch.Tensor) -> float:
    """The fraction of phases at the network's clamp (|phase| >= pi)."""
    return float((phase.detach().abs() >= math.pi - CLAMP_TOLERANCE).float().mean())


def gradient_norm(model: nn.Module) -> float:
    """The L2 norm of all gradients of `model` (0 where none flowed); non-finite if any gradient is."""
    norms = [p.grad.detach().norm() for p in model.parameters() if p.grad is not None]
    return float(torch.stack(norms).norm()) if norms else 0.0


class TrainingHealth:
    """Watches StepStats step by step; `verdict` says why training should stop (None while it is healthy).

    Stalled: `patience` consecutive steps with a zero gradient, or with at least `clamp_limit` of the output at
    the clamp. Diverged: a non-finite loss or gradient, or (after `warmup` steps) a smoothed loss above
    `rise_limit` times the lowest smoothed loss so far.
    """

    def __init__(self, patience: int = 10, clamp_limit: float = 0.99, rise_limit: float = 10.0,
                 warmup: int = 50, smoothing: float = 0.95) -> None:
        self.patience = patience
        self.clamp_limit = clamp_limit
        self.rise_limit = rise_limit
        self.warmup = warmup
        self.smoothing = smoothing
        self.steps = 0
        self._stalled = 0
        self._smoothed: float | None = None
        self._lowest = math.inf

    def update(self, stats: StepStats) -> str | None:
        """Take one step's stats; the verdict if training should stop there, else None."""
        self.steps += 1
        if not (math.isfinite(stats.loss) and math.isfinite(stats.grad_norm)):
            return (f"diverged at step {self.steps}: the loss or gradient is not finite (loss {stats.loss:g}, "
                    f"gradient norm {stats.grad_norm:g}); lower the learning rate")
        stuck = stats.grad_norm == 0.0 or stats.clamped >= self.clamp_limit
        self._stalled = self._stalled + 1 if stuck else 0
        if self._stalled >= self.patience:
            return (f"stopped learning at step {self.steps}: for {self.patience} steps the gradient was "
                    f"{stats.grad_norm:.3g} and {100 * stats.clamped:.1f} % of the output phase sat at the +-pi "
                    "clamp; lower the learning rate")
        self._smoothed = stats.loss if self._smoothed is None else (
            self.smoothing * self._smoothed + (1 - self.smoothing) * stats.loss)
        if self.steps > self.warmup:
            if self._smoothed > self.rise_limit * self._lowest:
                return (f"diverged at step {self.steps}: the smoothed loss {self._smoothed:.4g} rose above "
                        f"{self.rise_limit:g} x its lowest ({self._lowest:.4g}); lower the learning rate")
            self._lowest = min(self._lowest, self._smoothed)
        return None
