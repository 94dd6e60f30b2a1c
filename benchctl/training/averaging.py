"""Weight averaging (Polyak): an exponential moving average of a network's weights over the training steps.

At a constant learning rate the weights keep moving around the minimum from step to step, and so does the
validation score; their average sits nearer the middle (checkpoints/simulated/README.md measures what it gains).

torch's `AveragedModel` keeps the average; the rule it applies is the bias-corrected one Adam uses for its
moments: sum_t = decay sum_(t-1) + (1 - decay) w_t from sum_0 = 0, average = sum_t / (1 - decay^t), so a short
run is averaged over the steps it has, not pulled towards its first weights. In terms of the average a after n
steps (what `AveragedModel` holds): a' = (decay (1 - decay^n) a + (1 - decay) w) / (1 - decay^(n + 1)).
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel


class WeightAverage:
    """The bias-corrected exponential moving average of one model's floating-point weights and buffers."""

    def __init__(self, model: nn.Module, decay: float) -> None:
        if not 0 < decay < 1:
            raise ValueError(f"the average's decay must lie in (0, 1), got {decay}")
        self.decay = decay

        def average(averaged: torch.Tensor, current: torch.Tensor, count: torch.Tensor | int) -> torch.Tensor:
            if not averaged.is_floating_point():  # a counter (BatchNorm's batches seen): the model's own
                return current
            kept = decay * (1 - decay ** count)
            return (kept * averaged + (1 - decay) * current) / (1 - decay ** (count + 1))

        self.model = AveragedModel(model, avg_fn=average, use_buffers=True)

    @property
    def count(self) -> int:
        """Steps averaged so far."""
        return int(self.model.n_averaged)

    def update(self, model: nn.Module) -> None:
        """Fold in the model's weights after one more training step."""
        self.model.update_parameters(model)

    def state_dict(self, model: nn.Module) -> dict[str, torch.Tensor]:
        """`model`'s state dict with the averaged weights in place of its own (its own before any step)."""
        source = self.model.module if self.count else model
        return {key: value.detach().clone() for key, value in source.state_dict().items()}

    def averaged(self, model: nn.Module) -> nn.Module:
        """A copy of `model` holding the averaged weights (to validate or save; `model` trains on)."""
        return copy.deepcopy(self.model.module if self.count else model)

    def to_state(self) -> dict[str, Any]:
        """What a resumed run needs to continue the average exactly."""
        return {"decay": self.decay, "count": self.count,
                "average": {k: v.detach().cpu() for k, v in self.model.module.state_dict().items()}}

    def load_state(self, state: dict[str, Any]) -> None:
        """Continue the average `to_state` saved (its decay must be this one's)."""
        if float(state["decay"]) != self.decay:
            raise ValueError(f"the saved average has decay {state['decay']}, this run {self.decay}")
        self.model.module.load_state_dict(state["average"])
        self.model.n_averaged.fill_(int(state["count"]))
