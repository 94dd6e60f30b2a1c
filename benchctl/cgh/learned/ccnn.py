"""CCNN-CGH (Zhong et al. 2023) and its DCM variant: two small complex-valued networks around the propagation.

`ComplexUNet`: stride-2 3x3 complex convs down, each followed by a complex ReLU, then stride-2 4x4 complex
transposed convs back up, each followed by a complex ReLU except the last; the output of each down level is
added to the input of the matching up level (the innermost one excepted); the network returns the phase
(angle) of its complex output. Real inputs are read as amplitudes with zero phase.

- CCNN-CGH: generator 1-4-8-16-32 on the target amplitude, encoder 1-4-8-16 on the SLM field:
  42,260 parameters (published: about 42.3 K).
- DCM x4: complex unshuffle into 16 complex channels; each sub-network is one complex down conv 16 -> 32 and
  one complex transposed conv back, plus the sub-network's input (residual); LFMN merges the encoder's 16
  sub-holograms. Both sub-networks together hold 51,392 parameters; with LFMN x4 at N = 2 blocks the total
  is 97,476 at dim 24 (the 4K setting) and 112,714 at dim 28 (the 8K setting). The published "about 112.7 K"
  is therefore the 8K model's count to four digits; no reading of the 4K architecture reaches it (the
  nearest, 4x4 instead of 3x3 down convs, gives 111,812 and would contradict CCNN-CGH's 3x3 down convs).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from benchctl.cgh.learned.complex_layers import ComplexConv2d, ComplexConvTranspose2d, ComplexReLU
from benchctl.cgh.learned.dcm import Divided, divided_pair, pad_to_multiple

GENERATOR_CHANNELS = (1, 4, 8, 16, 32)
ENCODER_CHANNELS = (1, 4, 8, 16)
DCM_WIDTH = 32


class ComplexUNet(nn.Module):
    """Complex (or amplitude) (B, channels[0], H, W) -> phases (B, channels[0], H, W) in [-pi, pi]."""

    def __init__(self, channels: Sequence[int], input_residual: bool = False) -> None:
        super().__init__()
        if len(channels) < 2:
            raise ValueError(f"a complex U-Net needs at least two widths, got {tuple(channels)}")
        pairs = list(zip(channels[:-1], channels[1:]))
        self.multiple = 2 ** len(pairs)
        self.input_residual = input_residual
        self.downs = nn.ModuleList(nn.Sequential(ComplexConv2d(a, b, 3, stride=2, padding=1), ComplexReLU())
                                   for a, b in pairs)
        self.ups = nn.ModuleList(
            nn.Sequential(ComplexConvTranspose2d(b, a, 4, stride=2, padding=1), *([ComplexReLU()] if i else []))
            for i, (a, b) in reversed(list(enumerate(pairs))))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if not x.is_complex():
            x = torch.complex(x, torch.zeros_like(x))
        x = pad_to_multiple(x, self.multiple)
        out = x
        skips = []
        for down in self.downs:
            out = down(out)
            skips.append(out)
        skips.pop()  # the innermost level has no skip
        for up in self.ups:
            out = up(out)
            if skips:
                out = out + skips.pop()
        if self.input_residual:
            out = out + x
        return out.angle()[..., :h, :w]


def ccnn(factor: int = 1, merge: nn.Module | None = None) -> tuple[Divided, Divided]:
    """CCNN-CGH's generator and encoder; divided by `factor` > 1 they become the one-level DCM sub-networks.

    `merge` merges the encoder's r^2 sub-holograms (an `LFMN`; PixelShuffle by default).
    """
    if factor == 1:
        return divided_pair(ComplexUNet(GENERATOR_CHANNELS), ComplexUNet(ENCODER_CHANNELS), 1, merge)
    channels = (factor * factor, DCM_WIDTH)
    return divided_pair(ComplexUNet(channels, input_residual=True), ComplexUNet(channels, input_residual=True),
                        factor, merge)
