"""Complex-valued layers for CCNN-CGH: complex conv, complex transposed conv, complex ReLU.

A complex linear layer is a pair of real layers (W_r, W_i) applied as
(W_r * re - W_i * im) + i (W_r * im + W_i * re), each real layer with its own bias, as in the
complexPyTorch layers CCNN-CGH is built on (so the bias of the output is b_r - b_i + i (b_r + b_i) and a
complex layer holds twice the parameters of one real layer: the published 42.3 K of CCNN-CGH counts both).
"""

from __future__ import annotations

import torch
from torch import nn


class ComplexPair(nn.Module):
    """Applies the real layers `real` and `imag` to a complex tensor as one complex linear layer."""

    def __init__(self, real: nn.Module, imag: nn.Module) -> None:
        super().__init__()
        self.real = real
        self.imag = imag

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.complex(self.real(x.real) - self.imag(x.imag), self.real(x.imag) + self.imag(x.real))


class ComplexConv2d(ComplexPair):
    """Complex 2-D convolution (arguments as `nn.Conv2d`)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1,
                 padding: int = 0) -> None:
        super().__init__(*(nn.Conv2d(in_channels, out_channels, kernel_size, stride=stride, padding=padding)
                           for _ in range(2)))


class ComplexConvTranspose2d(ComplexPair):
    """Complex 2-D transposed convolution (arguments as `nn.ConvTranspose2d`)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, stride: int = 1,
                 padding: int = 0) -> None:
        super().__init__(*(nn.ConvTranspose2d(in_channels, out_channels, kernel_size, stride=stride,
                                              padding=padding) for _ in range(2)))


class ComplexReLU(nn.Module):
    """ReLU on the real and the imaginary parts separately."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.complex(torch.relu(x.real), torch.relu(x.imag))
