"""Learned hologram networks: HoloNet, CCNN-CGH and their divide-conquer-and-merge (DCM) variants.

`build_model(name, setup)` returns a module mapping the target amplitude (B, 1, H, W) on the SLM grid to the
SLM phase in [-pi, pi] (a network for scenes with depth, `DEPTH_METHODS`, reads the depth map too); the
networks propagate with the setup's propagator, always at full definition.
`model_info(name, shape)` describes a method and counts its parameters without an optical setup. Importing
this package registers every learned method (and `<name>+sgd`) in the method registry; the perceptual loss is
in `vgg`. Training and its data are workflows on disk (`benchctl.training`), checkpoint files too
(`benchctl.holograms.checkpoints`).
"""

from benchctl.cgh.learned.ccnn import ComplexUNet, ccnn
from benchctl.cgh.learned.complex_layers import ComplexConv2d, ComplexConvTranspose2d, ComplexReLU
from benchctl.cgh.learned.dcm import Divided, PhaseHologramNet, divided_pair, pad_to_multiple
from benchctl.cgh.learned.depth import DepthHologramNet
from benchctl.cgh.learned.holonet import AmplitudePhase, holonet
from benchctl.cgh.learned.lfmn import ECCM, GRN, LFM, LFMM, LFMN, PYRAMID_GROUPS, PyramidMerger, sublattice_groups
from benchctl.cgh.learned.models import (
    DEPTH_METHODS,
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
    "ComplexConv2d",
    "ComplexConvTranspose2d",
    "ComplexReLU",
    "ComplexUNet",
    "DEPTH_METHODS",
    "DepthHologramNet",
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
    "count_parameters",
    "divided_pair",
    "holonet",
    "model_info",
    "pad_to_multiple",
    "sublattice_groups",
    "tier",
]
