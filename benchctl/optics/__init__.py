"""Physics and metrics: propagation, colour, metrics (torch), phase encoding (numpy). Imports nothing else from
benchctl.

The names below are loaded from their modules on first use, so a torch-free part (`phase_encoding`; `geometry`: a
colour channel's optical geometry; `plan`: what a propagation will compute) can be imported without loading torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_HOME = {
    "linear_to_srgb": "colour",
    "srgb_to_linear": "colour",
    "amplitude_scores": "metrics",
    "colour_scores": "metrics",
    "crop_roi": "metrics",
    "lsq_scale": "metrics",
    "psnr": "metrics",
    "ssim": "metrics",
    "PhaseLUT": "phase_encoding",
    "gray_to_phase": "phase_encoding",
    "phase_to_gray": "phase_encoding",
    "FocalStackTarget": "focal_stack",
    "focal_stack_loss": "focal_stack",
    "focal_stack_scores": "focal_stack",
    "in_focus_masks": "focal_stack",
    "Geometry": "geometry",
    "MultiPlanePropagator": "multiplane",
    "PropagationPlan": "plan",
    "plan_propagation": "plan",
    "Propagator": "propagation",
    "PrunedPropagator": "propagation",
    "propagate": "propagation",
}

__all__ = sorted(_HOME)

def __getattr__(name: str) -> Any:
    """`benchctl.optics.NAME`: imported from its module when first asked for."""
    if name not in _HOME:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_HOME[name]}"), name)
    globals()[name] = value
    return value
