"""Complex-valued layers for CCNN-CGH: complex conv, complex transposed conv, complex ReLU.

A complex linear layer is a pair of real layers (W_r, W_i) applied as
(W_r * re - W_i * im) + i (W_r * im + W_i * re), each real layer with its own bias, as in the
complexPyTorch layers CCNN-CGH is built on (so the bias of the output is b_r - b_i + i (b_r + b_i) and a
complex layer holds twice the parameters of one real layer: the published 42.3 K of CCNN-CGH counts both).

The convolutions run as ONE real convolution of [re, im] stacked on the channels with the block weight
[[W_r, -W_i], [W_i, W_r]]: the same products as four convolutions, without four strided copies of the real and
imaginary parts and three more passes over the image (docs/benchmarks.md: CCNN-x4's inference time). The
parameters stay the pair's, so checkpoints are unchanged.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class ComplexPair(nn.Module):
    """Applies the real layers `real` and `imag` to a complex tensor as one complex linear layer."""

    def __init__(self, real: nn.Module, imag: nn.Module) -> None:
        super().__init__()
        self.real = real
        self.imag = imag

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.complex(self.real(x.real) - self.imag(x.imag), self.real(x.imag) + self.imag(x.real))


def _stacked(x: torch.Tensor) -> torch.Tensor:
    """A complex (B, C, H, W) tensor as real (B, 2C, H, W): [re, im] on the channels."""
    return torch.cat((x.real, x.imag), dim=1)


def _complex(y: torch.Tensor) -> torch.Tensor:
    """Real (B, 2C, H, W) [re, im] back to complex (B, C, H, W)."""
    re, im = y.chunk(2, dim=1)
    return torch.complex(re, im)


class ComplexConv2d(ComplexPair):
    """Complex 2-D convolution (arguments as `nn.Conv2d`)."""

    real: nn.Conv2d
    imag: nn.Conv2d

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1,
                 padding: int = 0) -> None:
        super().__init__(*(nn.Conv2d(in_channels, out_channels, kernel_size, stride=stride, padding=padding)
                           for _ in range(2)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        wr, wi = self.real.weight, self.imag.weight  # (out, in, k, k)
        weight = torch.cat((torch.cat((wr, -wi), dim=1), torch.cat((wi, wr), dim=1)), dim=0)
        br, bi = self.real.bias, self.imag.bias
        bias = None if br is None or bi is None else torch.cat((br - bi, br + bi))
        return _complex(F.conv2d(_stacked(x), weight, bias, self.real.stride, self.real.padding))


class ComplexConvTranspose2d(ComplexPair):
    """Complex 2-D transposed convolution (arguments as `nn.ConvTranspose2d`)."""

    real: nn.ConvTranspose2d
    imag: nn.ConvTranspose2d

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1,
                 padding: int = 0) -> None:
        super().__init__(*(nn.ConvTranspose2d(in_channels, out_channels, kernel_size, stride=stride,
                                              padding=padding) for _ in range(2)))
        self.stride, self.padding = stride, padding

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        wr, wi = self.real.weight, self.imag.weight  # (in, out, k, k)
        weight = torch.cat((torch.cat((wr, wi), dim=1), torch.cat((-wi, wr), dim=1)), dim=0)
        br, bi = self.real.bias, self.imag.bias
        bias = None if br is None or bi is None else torch.cat((br - bi, br + bi))
        return _complex(F.conv_transpose2d(_stacked(x), weight, bias, self.stride, self.padding))


class ComplexReLU(nn.Module):
    """ReLU on the real and the imaginary parts separately."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.complex(torch.relu(x.real), torch.relu(x.imag))
