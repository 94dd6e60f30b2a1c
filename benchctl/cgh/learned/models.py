"""The catalogue of learned methods: names -> networks with the paper's settings for the grid size.

Grid tiers by pixel count: up to 1088 x 1920 is "1080p", up to 2176 x 3840 "4k", above that "8k" (the
paper's grids are 1088 x 1920, 2176 x 3840 and 4352 x 7680). LFMN blocks: 4 at 1080p, 2 above, and always 2
for CCNN x4. LFMN dims: HoloNet x2 32 at 1080p / 24 above, x4 40 / 32, pyramid (both stages) 32 / 24;
CCNN x4 24 below 8K, 28 at 8K. These are the paper's public code's settings.

Ablations of the paper's Table 4 (HoloNet, 1080p settings): `holonet-ps2` / `-ps4` merge the encoder's
sub-holograms with a plain PixelShuffle ("SR -> None"); `holonet-lowdef2` propagates the sub-images at low
definition ("ASM at low definition", `dcm.LowDefinitionNet`); `holonet-dcm2-nolfm` / `-noeccm` / `-nogrn`
drop one part of LFMN.

For scenes with depth (`depth.DepthHologramNet`, the paper's future work): `holonet3d`, `holonet3d-dcm2`,
`holonet3d-dcm4`: HoloNet's networks with the depth map as a second generator input, divided and merged as
`holonet`, `holonet-dcm2`, `holonet-dcm4` (the same LFMN settings per tier). They are not refined by 2D SGD.

Every learned method, and each refined by SGD (`<name>+sgd`), is registered in the one method registry
(`benchctl.cgh.METHODS`) as a method that needs a checkpoint.

`model_info` counts trainable parameters from the networks alone, so it needs no optical setup and builds
no propagation kernel (at 8K with 2x padding one kernel takes about 1 GiB).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

from torch import nn

from benchctl.cgh.learned.ccnn import ccnn
from benchctl.cgh.learned.dcm import Divided, LowDefinitionNet, PhaseHologramNet
from benchctl.cgh.learned.depth import DepthHologramNet
from benchctl.cgh.learned.holonet import holonet
from benchctl.cgh.learned.lfmn import LFMN, PyramidMerger
from benchctl.cgh.method import REFINED_SUFFIX, Method, register
from benchctl.cgh.sgd import SGD
from benchctl.optics.setup import OpticalSetup

TIERS = (("1080p", 1088 * 1920), ("4k", 2176 * 3840), ("8k", None))
BLOCKS = {"1080p": 4, "4k": 2, "8k": 2}
FAMILIES: dict[str, Callable[[int, nn.Module | None], tuple[Divided, Divided]]] = {
    "holonet": holonet, "ccnn": ccnn, "holonet3d": functools.partial(holonet, inputs=2)}
DEPTH_FAMILIES = ("holonet3d",)
"""Families whose networks read a depth map beside the amplitude (`DepthHologramNet`)."""


@dataclass(frozen=True)
class Variant:
    """One learned method: network family, DCM factor, how the encoder merges, LFMN dims (and blocks, when
    not the tier's) per tier, LFMN parts removed, and whether the sub-images propagate at low definition."""

    family: str
    factor: int = 1
    merger: str = "pixel-shuffle"  # "pixel-shuffle" (also the classical r = 1), "lfmn" or "pyramid"
    dims: dict[str, tuple[int, ...]] | None = None
    blocks: int | None = None
    without: tuple[str, ...] = ()
    low_definition: bool = False


_X2_DIMS: dict[str, tuple[int, ...]] = {"1080p": (32,), "4k": (24,), "8k": (24,)}
_X4_DIMS: dict[str, tuple[int, ...]] = {"1080p": (40,), "4k": (32,), "8k": (32,)}
VARIANTS: dict[str, Variant] = {
    "holonet": Variant("holonet"),
    "holonet-dcm2": Variant("holonet", 2, "lfmn", _X2_DIMS),
    "holonet-dcm4": Variant("holonet", 4, "lfmn", _X4_DIMS),
    "holonet-pyramid": Variant("holonet", 4, "pyramid", {"1080p": (32, 32), "4k": (24, 24), "8k": (24, 24)}),
    "ccnn": Variant("ccnn"),
    "ccnn-dcm4": Variant("ccnn", 4, "lfmn", {"1080p": (24,), "4k": (24,), "8k": (28,)}, blocks=2),
    "holonet-ps2": Variant("holonet", 2),
    "holonet-ps4": Variant("holonet", 4),
    "holonet-lowdef2": Variant("holonet", 2, "lfmn", _X2_DIMS, low_definition=True),
    "holonet-dcm2-nolfm": Variant("holonet", 2, "lfmn", _X2_DIMS, without=("lfm",)),
    "holonet-dcm2-noeccm": Variant("holonet", 2, "lfmn", _X2_DIMS, without=("eccm",)),
    "holonet-dcm2-nogrn": Variant("holonet", 2, "lfmn", _X2_DIMS, without=("grn",)),
    "holonet3d": Variant("holonet3d"),
    "holonet3d-dcm2": Variant("holonet3d", 2, "lfmn", _X2_DIMS),
    "holonet3d-dcm4": Variant("holonet3d", 4, "lfmn", _X4_DIMS),
}
LEARNED_METHODS = tuple(VARIANTS)
"""The networks: the registered methods that need a checkpoint and refine no other method."""
DEPTH_METHODS = tuple(name for name, variant in VARIANTS.items() if variant.family in DEPTH_FAMILIES)
"""The networks for scenes with depth (amplitude and depth in; trained on a focal stack)."""


def _register_methods() -> None:
    """Every network as a method that needs a checkpoint, then each 2D one refined by SGD (`<name>+sgd`)."""
    for name, variant in VARIANTS.items():
        register(Method(name, f"trained {variant.family} network", None, None, variant.family,
                        reads_depth=name in DEPTH_METHODS))
    for name, variant in VARIANTS.items():
        if name in DEPTH_METHODS:
            continue
        register(Method(f"{name}{REFINED_SUFFIX}", f"{name}'s hologram refined by SGD", SGD.default_iterations, None,
                        variant.family, refines=name))


_register_methods()

PAPER_PARAMETERS: dict[str, tuple[tuple[int, int], float]] = {
    "holonet": ((1088, 1920), 2.87e6),
    "holonet-dcm2": ((1088, 1920), 3.01e6),
    "holonet-dcm4": ((1088, 1920), 3.11e6),
    "holonet-pyramid": ((1088, 1920), 3.17e6),
    "ccnn": ((2176, 3840), 42.3e3),
    "ccnn-dcm4": ((4352, 7680), 112.7e3),  # the 8K model's count: see benchctl.cgh.learned.ccnn
}
"""Published parameter counts and the grid whose settings reproduce them."""


def tier(shape: tuple[int, int]) -> str:
    """The paper's resolution tier ("1080p", "4k" or "8k") whose settings apply to an H x W grid."""
    pixels = shape[0] * shape[1]
    return next(name for name, limit in TIERS if limit is None or pixels <= limit)


def _variant(name: str) -> Variant:
    try:
        return VARIANTS[name]
    except KeyError:
        raise ValueError(f"unknown learned method {name!r}; known: {', '.join(LEARNED_METHODS)}") from None


def _merger(variant: Variant, grid_tier: str) -> nn.Module | None:
    if variant.dims is None:
        return None
    dims, blocks = variant.dims[grid_tier], _blocks(variant, grid_tier)
    if variant.merger == "pyramid":
        return PyramidMerger((dims[0], dims[1]), blocks)
    return LFMN(variant.factor, dims[0], blocks, without=variant.without)


def _blocks(variant: Variant, grid_tier: str) -> int:
    return variant.blocks or BLOCKS[grid_tier]


def build_networks(name: str, shape: tuple[int, int]) -> tuple[Divided, Divided]:
    """The phase generator and phase encoder of method `name` with the settings for an H x W grid."""
    variant = _variant(name)
    return FAMILIES[variant.family](variant.factor, _merger(variant, tier(shape)))


def build_model(name: str, setup: OpticalSetup,
                depth_range_m: tuple[float, float] | None = None) -> PhaseHologramNet:
    """Method `name` for `setup`: target amplitude (B, 1, H, W) -> SLM phase (B, 1, H, W) in [-pi, pi]; a network
    for scenes with depth also reads the depth (`DepthHologramNet`), over `depth_range_m` (near, far) metres."""
    variant = _variant(name)
    if variant.family in DEPTH_FAMILIES:
        return DepthHologramNet(*build_networks(name, setup.shape), setup, depth_range_m)
    net = LowDefinitionNet if variant.low_definition else PhaseHologramNet
    return net(*build_networks(name, setup.shape), setup)


def count_parameters(module: nn.Module) -> int:
    """Trainable parameters (BatchNorm running statistics are buffers, not counted)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def model_info(name: str, shape: tuple[int, int]) -> dict[str, object]:
    """What method `name` is on an H x W grid: family, factor, merger, tier, LFMN settings, parameter counts."""
    variant = _variant(name)
    grid_tier = tier(shape)
    generator, encoder = build_networks(name, shape)
    return {
        "name": name,
        "family": variant.family,
        "factor": variant.factor,
        "merger": variant.merger,
        "tier": grid_tier,
        "lfmn_dims": variant.dims[grid_tier] if variant.dims else None,
        "lfmn_blocks": _blocks(variant, grid_tier) if variant.dims else None,
        "lfmn_without": variant.without,
        "low_definition": variant.low_definition,
        "generator_parameters": count_parameters(generator),
        "encoder_parameters": count_parameters(encoder),
        "parameters": count_parameters(generator) + count_parameters(encoder),
    }
