"""Physics and metrics in torch: propagation, colour, metrics, phase encoding. Imports nothing else from benchctl."""

from benchctl.optics.colour import linear_to_srgb, srgb_to_linear
from benchctl.optics.metrics import amplitude_scores, colour_scores, crop_roi, lsq_scale, psnr, ssim
from benchctl.optics.phase_encoding import PhaseLUT, gray_to_phase, phase_to_gray
from benchctl.optics.propagation import PropagationPlan, Propagator, plan_propagation, propagate

__all__ = [
    "PhaseLUT",
    "amplitude_scores",
    "colour_scores",
    "PropagationPlan",
    "Propagator",
    "crop_roi",
    "gray_to_phase",
    "linear_to_srgb",
    "lsq_scale",
    "phase_to_gray",
    "plan_propagation",
    "propagate",
    "psnr",
    "srgb_to_linear",
    "ssim",
]
