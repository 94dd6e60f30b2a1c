"""HoloNet (Peng et al. 2020) and its DCM variants: two U-Nets around a full-definition propagation.

The phase generator U-Net maps the target amplitude to the target-plane phase; the phase encoder U-Net maps
(amplitude, phase) of the SLM field to the SLM phase. Divided by r, the generator sees r^2 amplitude
sub-images and predicts r^2 phases; the encoder sees 2 r^2 channels (the r^2 amplitude sub-images, then the
r^2 phase sub-images, the channel order of a pixel unshuffle of the 2-channel (amplitude, phase) image) and
predicts r^2 sub-holograms. The U-Nets keep their widths (16-32-64-128): only their input and output
channels change, as the paper states. An encoder merged by LFMN (or the pyramid) returns its output unclamped,
as in the paper's code: LFMN reads values beyond [-pi, pi] and clamps only its own output.
"""

from __future__ import annotations

import torch
from torch import nn

from benchctl.cgh.learned.dcm import Divided, divided_pair
from benchctl.cgh.learned.unet import UNet


class AmplitudePhase(nn.Module):
    """Complex (B, C, h, w) -> real (B, 2C, h, w): the C amplitudes, then the C phases (in [-pi, pi])."""

    def forward(self, field: torch.Tensor) -> torch.Tensor:
        return torch.cat([field.abs(), field.angle()], dim=1)


def holonet(factor: int = 1, merge: nn.Module | None = None, inputs: int = 1) -> tuple[Divided, Divided]:
    """HoloNet's phase generator and phase encoder, divided by `factor` (1: the original HoloNet).

    `merge` merges the encoder's r^2 sub-holograms (an `LFMN` or `PyramidMerger`; PixelShuffle by default).
    `inputs`: maps the generator reads per pixel (1: the amplitude; 2: amplitude and depth, `depth.holonet3d`),
    each divided into r^2 sub-images.
    """
    channels = factor * factor
    encoder = UNet(2 * channels, channels, clamp=merge is None)
    return divided_pair(UNet(inputs * channels, channels), nn.Sequential(AmplitudePhase(), encoder), factor, merge)
