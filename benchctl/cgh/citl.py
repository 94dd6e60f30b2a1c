"""Camera-in-the-loop (CITL) optimisation's loss (Peng et al. 2020, "Neural holography with camera-in-the-loop
training"): the error of what the camera captured of a phase, differentiated through the propagation model.

The camera's image has no gradient. The straight-through trick takes the loss's value from the capture and its
gradient from the model: with m the model's ROI amplitude of the phase and c the registered captured amplitude,
each least-squares scaled to the target t (s_m, s_c),

    estimate = s_m m + (s_c c - s_m m).detach()        forward: s_c c;   backward: d(s_m m)/d phase
    loss = mean((estimate - t)^2)

so dloss/dphase = 2/N sum (s_c c - t) s_m dm/dphase: the model's Jacobian applied to the error the camera saw.
When the capture equals the model (c proportional to m) this is exactly SGD's gradient (`sgd.roi_loss`), and the
model's mismatch with the bench then only bends the direction, never the value being minimised.
"""

from __future__ import annotations

import torch

from benchctl.optics.metrics import lsq_scale
from benchctl.optics.setup import OpticalSetup


def straight_through_loss(phase: torch.Tensor, captured: torch.Tensor, target: torch.Tensor,
                          setup: OpticalSetup) -> torch.Tensor:
    """MSE over the ROI of the least-squares-scaled captured amplitude `captured` (roi_h, roi_w) against the
    target amplitude `target` (ROI, same shape), with the gradient of the model's reconstruction of `phase`
    (H, W), as the SLM shows it (`setup.displayed`), in its place (module docstring). Scales are held constant
    for autograd, as in SGD."""
    model = setup.reconstruct_roi(setup.displayed(phase))
    if captured.shape != model.shape or target.shape != model.shape:
        raise ValueError(f"captured {tuple(captured.shape)} and target {tuple(target.shape)} must be the ROI "
                         f"{tuple(model.shape)}")
    captured = captured.to(model.dtype)
    estimate = lsq_scale(model.detach(), target) * model
    seen = lsq_scale(captured, target) * captured
    return torch.nn.functional.mse_loss(estimate + (seen - estimate).detach(), target)
