"""The one sRGB <-> linear-intensity conversion (IEC 61966-2-1 transfer curve), differentiable in torch.

Targets are defined in sRGB but light adds in linear intensity, so every conversion between the two goes
through here. Negative inputs are clamped to 0 (their gradient is 0). Values above 1 are not clipped:
the curve's power segment continues, so over-bright reconstructions stay ordered and keep their gradient.
Gradients are finite everywhere, including at 0.
"""

from __future__ import annotations

import torch

_SRGB_KNEE = 0.04045  # sRGB value where the linear segment meets the power segment
_LINEAR_KNEE = 0.0031308  # the same point in linear intensity
_SLOPE = 12.92
_GAMMA = 2.4
_OFFSET = 0.055


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """Decode sRGB values (any shape) to linear intensity; negatives become 0, values above 1 extrapolate."""
    x = x.clamp(min=0.0)
    power = ((x.clamp(min=_SRGB_KNEE) + _OFFSET) / (1.0 + _OFFSET)) ** _GAMMA
    return torch.where(x <= _SRGB_KNEE, x / _SLOPE, power)


def linear_to_srgb(x: torch.Tensor) -> torch.Tensor:
    """Encode linear intensity (any shape) as sRGB; negatives become 0, values above 1 extrapolate."""
    x = x.clamp(min=0.0)
    # The clamp keeps x ** (1 / 2.4) away from 0, where its derivative is infinite; torch.where would
    # otherwise turn that unused infinity into a NaN gradient.
    power = (1.0 + _OFFSET) * x.clamp(min=_LINEAR_KNEE) ** (1.0 / _GAMMA) - _OFFSET
    return torch.where(x <= _LINEAR_KNEE, x * _SLOPE, power)
