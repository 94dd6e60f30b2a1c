"""LFMN, the paper's light holographic super-resolution network that merges r^2 sub-holograms, and its pyramid.

LFMN (x r): conv3x3 r^2 -> dim, GRN, N blocks of [x = LFM(x) + x; x = ECCM(x) + x], conv3x3 dim -> r^2,
plus the r^2-channel input (global residual), then PixelShuffle(r) and Hardtanh(-pi, pi).

- LFM (local feature modulation, a gate): conv3x3 dim -> dim/2, LeakyReLU(0.1), conv3x3 dim/2 -> dim/2,
  LeakyReLU(0.1), conv3x3 dim/2 -> dim, Sigmoid; the result multiplies the module's input.
- ECCM (enhanced convolutional channel mixer): conv3x3 dim -> 1.25 dim (rounded down), LeakyReLU(0.1),
  conv3x3 back to dim.
- GRN (ConvNeXt-V2 global response normalisation, channels first): G = L2 norm of x over (H, W),
  N = G / (mean of G over channels + 1e-6), out = gamma * (x * N) + beta + x, gamma and beta zero at start
  so that the GRN starts as the identity.

All convs have biases and zero padding. Parameter counts at 1080p (N = 4): x2 dim 32 -> 141,188;
x4 dim 40 -> 228,336; with HoloNet's two U-Nets that gives 3.013 M and 3.112 M (published 3.01 M, 3.11 M).

Pyramid (recursive merge, x4 = x2 twice): the 16 sub-holograms of a 4x4 unshuffle split into four groups,
each the four channels of one 2x2 sub-lattice (`sublattice_groups`: 1-based [1,3,9,11], [2,4,10,12],
[5,7,13,15], [6,8,14,16]); one x2 LFMN without its final Hardtanh, shared by the four groups, merges each
group into one half-definition image, and those four images are exactly the 2x2 unshuffle of the full
hologram, so a second, independent x2 LFMN merges them.

Both pyramid stages have the same dim (32 at 1080p, 24 above, ECCM hidden widths 40 and 30), as in the
paper's code: the pyramid HoloNet then holds 3,165,992 parameters (published 3.17 M).

Ablations (the paper's Table 4, "LFM / ECCM / GRN -> None"): `LFMN(..., without=("lfm",))` and so on drop
that part, i.e. the block or the network goes on without it (no residual around a removed part).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

LEAKY_SLOPE = 0.1
ECCM_EXPANSION = 1.25
GRN_EPS = 1e-6


def _conv3x3(in_channels: int, out_channels: int) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, 3, padding=1)


class GRN(nn.Module):
    """Global response normalisation (channels first); the identity while gamma = beta = 0 (their start)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.zeros(1, dim, 1, 1))
        self.beta = nn.Parameter(torch.zeros(1, dim, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        g = torch.linalg.vector_norm(x, dim=(-2, -1), keepdim=True)
        n = g / (g.mean(dim=1, keepdim=True) + GRN_EPS)
        return self.gamma * (x * n) + self.beta + x


class LFM(nn.Module):
    """Local feature modulation: a sigmoid gate computed from local features, multiplied with the input."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        hidden = dim // 2
        self.gate = nn.Sequential(_conv3x3(dim, hidden), nn.LeakyReLU(LEAKY_SLOPE),
                                  _conv3x3(hidden, hidden), nn.LeakyReLU(LEAKY_SLOPE),
                                  _conv3x3(hidden, dim), nn.Sigmoid())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.gate(x) * x


class ECCM(nn.Sequential):
    """Enhanced convolutional channel mixer: 3x3 dim -> 1.25 dim, LeakyReLU(0.1), 3x3 back to dim."""

    def __init__(self, dim: int) -> None:
        hidden = int(dim * ECCM_EXPANSION)
        super().__init__(_conv3x3(dim, hidden), nn.LeakyReLU(LEAKY_SLOPE), _conv3x3(hidden, dim))


LFMN_PARTS = ("lfm", "eccm", "grn")
"""The LFMN parts an ablation may remove."""


class LFMM(nn.Module):
    """Local feature mixing module: x = LFM(x) + x, then x = ECCM(x) + x (a removed part is skipped)."""

    def __init__(self, dim: int, lfm: bool = True, eccm: bool = True) -> None:
        super().__init__()
        self.lfm = LFM(dim) if lfm else None
        self.eccm = ECCM(dim) if eccm else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.lfm is not None:
            x = self.lfm(x) + x
        return self.eccm(x) + x if self.eccm is not None else x


class LFMN(nn.Module):
    """(B, r^2, h, w) sub-holograms -> (B, 1, r h, r w) hologram (in [-pi, pi] when `hardtanh`).

    `without` names parts removed for an ablation (any of `LFMN_PARTS`).
    """

    def __init__(self, factor: int, dim: int, blocks: int, hardtanh: bool = True,
                 without: tuple[str, ...] = ()) -> None:
        super().__init__()
        unknown = set(without) - set(LFMN_PARTS)
        if unknown:
            raise ValueError(f"unknown LFMN part(s) {sorted(unknown)}; parts: {', '.join(LFMN_PARTS)}")
        channels = factor * factor
        self.factor = factor
        self.head = _conv3x3(channels, dim)
        self.grn = GRN(dim) if "grn" not in without else nn.Identity()
        self.body = nn.Sequential(*(LFMM(dim, "lfm" not in without, "eccm" not in without) for _ in range(blocks)))
        self.tail = _conv3x3(dim, channels)
        self.clamp = nn.Hardtanh(-math.pi, math.pi) if hardtanh else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        features = self.body(self.grn(self.head(x)))
        return self.clamp(F.pixel_shuffle(self.tail(features) + x, self.factor))


def sublattice_groups(factor: int, step: int) -> tuple[tuple[int, ...], ...]:
    """0-based channels of a `factor` x `factor` pixel unshuffle, grouped by `step` x `step` sub-lattice.

    Channel i * factor + j holds pixels (factor a + i, factor b + j). Group (p, q) (p, q < step, in row-major
    order) holds the channels with i = p, j = q modulo `step`, ordered row-major in (i // step, j // step):
    PixelShuffle(factor // step) of one group gives the pixels (step m + p, step n + q), i.e. channel
    step p + q of a `step` x `step` unshuffle of the full image.
    """
    if factor % step:
        raise ValueError(f"step {step} does not divide factor {factor}")
    inner = factor // step
    return tuple(tuple((step * u + p) * factor + step * v + q for u in range(inner) for v in range(inner))
                 for p in range(step) for q in range(step))


PYRAMID_GROUPS = sublattice_groups(4, 2)
"""The pyramid's channel groups (0-based); the paper's 1-based [1,3,9,11], [2,4,10,12], [5,7,13,15], [6,8,14,16]."""


class PyramidMerger(nn.Module):
    """x4 merge in two x2 stages: a shared LFMN per 2x2 sub-lattice group, then an independent LFMN."""

    groups: torch.Tensor  # a buffer, registered in __init__

    def __init__(self, dims: tuple[int, int], blocks: int) -> None:
        super().__init__()
        self.register_buffer("groups", torch.tensor(PYRAMID_GROUPS).flatten(), persistent=False)
        self.stage1 = LFMN(2, dims[0], blocks, hardtanh=False)
        self.stage2 = LFMN(2, dims[1], blocks)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, _, h, w = x.shape
        groups = x.index_select(1, self.groups).reshape(b * 4, 4, h, w)  # the groups share stage 1's weights
        merged = self.stage1(groups).reshape(b, 4, 2 * h, 2 * w)
        return self.stage2(merged)
