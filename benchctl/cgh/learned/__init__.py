"""Learned hologram networks: HoloNet, CCNN-CGH and their divide-conquer-and-merge (DCM) variants.

`build_model(name, setup)` returns a module mapping the target amplitude (B, 1, H, W) on the SLM grid to the
SLM phase in [-pi, pi]; the networks propagate with the setup's propagator, always at full definition.
`model_info(name, shape)` describes a method and counts its parameters without an optical setup.
Training lives in `training` (data in `data`, the perceptual loss in `vgg`), checkpoints in `checkpoint`
(`find_checkpoint` finds the shipped ones), and `inference.learned_method` / `resolve_method` turn a
checkpoint into a hologram `Method`.
"""

from benchctl.cgh.learned.ccnn import ComplexUNet, ccnn
from benchctl.cgh.learned.checkpoint import (
    Checkpoint,
    checkpoint_problem,
    find_checkpoint,
    read_checkpoint,
)
from benchctl.cgh.learned.complex_layers import ComplexConv2d, ComplexConvTranspose2d, ComplexReLU
from benchctl.cgh.learned.dcm import Divided, PhaseHologramNet, divided_pair, pad_to_multiple
from benchctl.cgh.learned.holonet import AmplitudePhase, holonet
from benchctl.cgh.learned.inference import learned_method, resolve_method
from benchctl.cgh.learned.lfmn import ECCM, GRN, LFM, LFMM, LFMN, PYRAMID_GROUPS, PyramidMerger, sublattice_groups
from benchctl.cgh.learned.models import (
    LEARNED_METHODS,
    PAPER_PARAMETERS,
    build_model,
    build_networks,
    count_parameters,
    model_info,
    tier,
)
from benchctl.cgh.learned.unet import UNet

__all__ = [
    "AmplitudePhase",
    "Checkpoint",
    "ComplexConv2d",
    "ComplexConvTranspose2d",
    "ComplexReLU",
    "ComplexUNet",
    "Divided",
    "ECCM",
    "GRN",
    "LEARNED_METHODS",
    "LFM",
    "LFMM",
    "LFMN",
    "PAPER_PARAMETERS",
    "PYRAMID_GROUPS",
    "PhaseHologramNet",
    "PyramidMerger",
    "UNet",
    "build_model",
    "build_networks",
    "ccnn",
    "checkpoint_problem",
    "count_parameters",
    "divided_pair",
    "find_checkpoint",
    "holonet",
    "learned_method",
    "model_info",
    "pad_to_multiple",
    "read_checkpoint",
    "resolve_method",
    "sublattice_groups",
    "tier",
]
