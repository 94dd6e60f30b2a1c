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

A scene with depth is optimised on its focal stack the same way (`straight_through_stack_loss`): each plane captured
with the camera focused there, the loss the masked focal-stack loss of the captures (each plane where the scene is in
focus there), its gradient through the model's multi-plane propagation.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from benchctl.optics.focal_stack import stack_scale
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


def straight_through_stack_loss(phase: torch.Tensor, captured: torch.Tensor, target: torch.Tensor,
                                masks: torch.Tensor, planes_m: Sequence[float], setup: OpticalSetup) -> torch.Tensor:
    """The focal-stack form of `straight_through_loss`: `captured` (K, h, w) holds the amplitude captured with the
    camera focused at each of the planes `planes_m`; the value is `focal_stack_loss`'s (each plane's error where the
    scene is in focus there, `masks` (K, h, w), against `target` (h, w), one least-squares scale per stack) of the
    captures, the gradient that of the model's focal stack of `phase` as the SLM shows it. With one plane and a mask
    of ones it is `straight_through_loss` at that plane."""
    model = setup.reconstruct_planes_roi(setup.displayed(phase), planes_m)
    if captured.shape != model.shape or masks.shape != model.shape or target.shape != model.shape[-2:]:
        raise ValueError(f"captured {tuple(captured.shape)}, masks {tuple(masks.shape)} and target "
                         f"{tuple(target.shape)} must be the focal stack {tuple(model.shape)} and one of its planes")
    captured, masks = captured.to(model.dtype), masks.to(model.dtype)
    estimate = stack_scale(model.detach(), target, masks) * model
    seen = stack_scale(captured, target, masks) * captured
    value = estimate + (seen - estimate).detach()
    return (masks * (value - target).square()).sum() / (target.shape[-2] * target.shape[-1])
