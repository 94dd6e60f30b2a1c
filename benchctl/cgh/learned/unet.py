"""HoloNet's U-Net (Peng et al. 2020), the phase generator and the phase encoder of HoloNet.

Layout (4 levels, 16 base features: 16-32-64-128), as in HoloNet's public code, which the published
parameter count (2.87 M for both U-Nets) pins:

- in: 3x3 conv -> BatchNorm -> LeakyReLU(0.2);
- each level down: 3x3 conv (same width) -> BN -> LeakyReLU(0.2), then 4x4 stride-2 conv -> BN -> LeakyReLU(0.2);
- each level up: 4x4 stride-2 transposed conv -> BN -> ReLU, then 3x3 conv -> BN -> ReLU; the level's input
  is concatenated to its output (skip);
- the innermost level works at 1/16 of the input size and has no BatchNorm (its convs carry biases instead);
- out: linear 3x3 conv with bias -> Hardtanh(-pi, pi); without the Hardtanh (`clamp=False`) when an LFMN
  merges the output (the paper's code: the DCM encoder returns its raw output and LFMN clamps at its end).

Every 3x3 and 4x4 conv uses reflection padding; convs followed by BatchNorm have no bias. Counted
parameters are the trainable ones (BatchNorm's affine weights, not its running statistics). The extra 3x3
conv before each down conv and after each transposed conv is what brings the count to the published figure:
without them the two U-Nets would hold 2.08 M.

Inputs whose sides 2^levels does not divide are zero-padded at the bottom / right and cropped back.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from benchctl.cgh.learned.dcm import pad_to_multiple


def _conv(in_channels: int, out_channels: int, kernel_size: int, stride: int, norm: bool) -> list[nn.Module]:
    """Reflection-padded conv, then BatchNorm (no conv bias) or nothing (conv bias)."""
    layers: list[nn.Module] = [nn.ReflectionPad2d(1),
                               nn.Conv2d(in_channels, out_channels, kernel_size, stride=stride, bias=not norm)]
    if norm:
        layers.append(nn.BatchNorm2d(out_channels))
    return layers


def _down(outer: int, inner: int, norm: bool) -> nn.Sequential:
    return nn.Sequential(*_conv(outer, outer, 3, 1, norm), nn.LeakyReLU(0.2),
                         *_conv(outer, inner, 4, 2, norm), nn.LeakyReLU(0.2))


def _up(in_channels: int, outer: int, norm: bool) -> nn.Sequential:
    layers: list[nn.Module] = [nn.ConvTranspose2d(in_channels, outer, 4, stride=2, padding=1, bias=not norm)]
    if norm:
        layers.append(nn.BatchNorm2d(outer))
    return nn.Sequential(*layers, nn.ReLU(), *_conv(outer, outer, 3, 1, norm), nn.ReLU())


class UNet(nn.Module):
    """(B, in_channels, H, W) -> (B, out_channels, H, W) phases, in [-pi, pi] when `clamp`; HoloNet's U-Net."""

    def __init__(self, in_channels: int, out_channels: int, features: int = 16, levels: int = 4,
                 clamp: bool = True) -> None:
        super().__init__()
        if levels < 1:
            raise ValueError(f"a U-Net needs at least one level, got {levels}")
        self.multiple = 2**levels
        widths = [features * 2**i for i in range(levels)]
        inners = widths[1:] + widths[-1:]  # the innermost level keeps its width
        self.inp = nn.Sequential(*_conv(in_channels, features, 3, 1, True), nn.LeakyReLU(0.2))
        self.downs = nn.ModuleList(
            _down(outer, inner, norm=i < levels - 1) for i, (outer, inner) in enumerate(zip(widths, inners)))
        # Up path input: the innermost down output, else the concatenation (skip + up) from the level below.
        self.ups = nn.ModuleList(
            _up(inner if i == levels - 1 else 2 * inner, outer, norm=i < levels - 1)
            for i, (outer, inner) in enumerate(zip(widths, inners)))
        self.out = nn.Sequential(nn.ReflectionPad2d(1), nn.Conv2d(2 * features, out_channels, 3),
                                 nn.Hardtanh(-math.pi, math.pi) if clamp else nn.Identity())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        x = self.inp(pad_to_multiple(x, self.multiple))
        skips = []
        for down in self.downs:
            skips.append(x)
            x = down(x)
        for up, skip in zip(reversed(self.ups), reversed(skips)):
            x = torch.cat([skip, up(x)], dim=1)
        return self.out(x)[..., :h, :w]
