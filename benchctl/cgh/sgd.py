"""Stochastic gradient descent on the SLM phase (Adam), fitting the simulated reconstruction to the target.

Loss: MSE between s * |P_{+z}(exp(i phase))| and the target, over the ROI only, with a learnable scale s
(a phase-only hologram cannot set the image's brightness, so s absorbs it). Defaults follow the published
neural-holography settings: Adam, phase lr 8e-3, scale lr 2e-3, 500 iterations, initial phase uniform in
[-0.5, 0.5]; s starts where the first reconstruction's ROI mean equals the target's.
"""

from __future__ import annotations

from typing import Optional

import torch

from benchctl.cgh.method import Method, Progress, register
from benchctl.optics.setup import OpticalSetup

DEFAULT_ITERATIONS = 500
PHASE_LR = 8e-3
SCALE_LR = 2e-3


def roi_loss(phase: torch.Tensor, scale: torch.Tensor, target: torch.Tensor, setup: OpticalSetup) -> torch.Tensor:
    """MSE over the ROI between scale * reconstruction of `phase` and `target` (both on the SLM grid)."""
    rows, cols = setup.roi_slices
    recon = setup.reconstruct(phase)[..., rows, cols]
    return torch.nn.functional.mse_loss(scale * recon, target[..., rows, cols])


def initial_scale(phase: torch.Tensor, target: torch.Tensor, setup: OpticalSetup) -> torch.Tensor:
    """The scale at which the reconstruction of `phase` has the target's mean over the ROI (1 if it is dark)."""
    rows, cols = setup.roi_slices
    with torch.no_grad():
        recon_mean = setup.reconstruct(phase)[rows, cols].mean()
        target_mean = target[rows, cols].mean()
        return torch.where(recon_mean > 0, target_mean / recon_mean, torch.ones_like(recon_mean))


def _sgd(target: torch.Tensor, setup: OpticalSetup, iterations: Optional[int], seed: int,
         progress: Optional[Progress]) -> torch.Tensor:
    assert iterations is not None  # Method resolves the default for iterative methods
    generator = torch.Generator(device=target.device).manual_seed(seed)
    # Optimise even when called under no_grad or inference_mode; the clone makes the target a normal tensor.
    with torch.inference_mode(False), torch.enable_grad():
        target = target.clone()
        phase = torch.rand(target.shape, generator=generator, device=target.device) - 0.5
        scale = initial_scale(phase, target, setup)
        phase.requires_grad_()
        scale.requires_grad_()
        optimiser = torch.optim.Adam([{"params": [phase], "lr": PHASE_LR}, {"params": [scale], "lr": SCALE_LR}])
        for done in range(1, iterations + 1):
            optimiser.zero_grad(set_to_none=True)
            roi_loss(phase, scale, target, setup).backward()
            optimiser.step()
            if progress is not None:
                progress(done, iterations)
    return phase.detach()


SGD = register(Method(
    name="sgd",
    description="Adam on the SLM phase and a brightness scale, minimising the simulated ROI error",
    default_iterations=DEFAULT_ITERATIONS,
    algorithm=_sgd,
))
