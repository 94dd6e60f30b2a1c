"""Divide-conquer-and-merge (DCM): the frame every learned method here shares, classical or divided.

A learned hologram network is two sub-networks around one propagation (`PhaseHologramNet`):
the phase generator turns the target amplitude into a phase at the target plane; amplitude * exp(i phase)
is propagated to the SLM (-z) on the FULL grid; the phase encoder turns that SLM field into the SLM phase.

DCM (`Divided`) wraps each sub-network: PixelUnshuffle(r) splits the input into r^2 sub-images of
H/r x W/r, the sub-network runs on those (channels r^2 for the generator, 2 r^2 for HoloNet's encoder),
and a merger puts the result back at full definition: PixelShuffle(r) for the generator, the LFMN
super-resolution network (or the pyramid of LFMNs) for the encoder. With r = 1 and PixelShuffle(1) the same
wrapper is the classical network, so baselines and DCM variants run one code path.

Only the sub-networks see low definition: the propagation always runs on the full SLM grid (the paper's
ablation: propagating sub-holograms at low definition drops PSNR to 16.6 dB).

Sizes r does not divide are zero-padded at the bottom / right and cropped after the merge; padding at the
far edges keeps pixel (0, 0) at sub-lattice offset (0, 0), so the sub-images mean the same on every grid.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from benchctl.optics.setup import OpticalSetup


def pad_to_multiple(x: torch.Tensor, multiple: int) -> torch.Tensor:
    """`x` (..., H, W) zero-padded at the bottom and right to the next multiples of `multiple` (real or complex)."""
    h, w = x.shape[-2:]
    pad_h, pad_w = -h % multiple, -w % multiple
    if pad_h == 0 and pad_w == 0:
        return x
    return F.pad(x, (0, pad_w, 0, pad_h))


class Divided(nn.Module):
    """PixelUnshuffle(r) -> `subnet` on the r^2 sub-images -> `merge` back to full definition -> crop.

    `subnet` maps (B, r^2 C, H/r, W/r) to (B, r^2, H/r, W/r) phases; `merge` maps those to (B, 1, H, W).
    Real and complex inputs are both divided as they are (a complex unshuffle for CCNN).
    """

    def __init__(self, subnet: nn.Module, factor: int, merge: nn.Module) -> None:
        super().__init__()
        if factor < 1:
            raise ValueError(f"the DCM factor must be >= 1, got {factor}")
        self.factor = factor
        self.subnet = subnet
        self.merge = merge

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        sub_images = F.pixel_unshuffle(pad_to_multiple(x, self.factor), self.factor)
        return self.merge(self.subnet(sub_images))[..., :h, :w]


def divided_pair(generator: nn.Module, encoder: nn.Module, factor: int,
                 merge: nn.Module | None = None) -> tuple[Divided, Divided]:
    """The DCM phase generator (merged by PixelShuffle) and phase encoder (merged by `merge`, default PixelShuffle)."""
    encoder_merge = nn.PixelShuffle(factor) if merge is None else merge
    return Divided(generator, factor, nn.PixelShuffle(factor)), Divided(encoder, factor, encoder_merge)


class PhaseHologramNet(nn.Module):
    """Target amplitude (B, 1, H, W) on the SLM grid -> SLM phase (B, 1, H, W) in [-pi, pi].

    generator(amplitude) -> target-plane phase; amplitude * exp(i phase) propagated target -> SLM (-z) at
    full definition with the setup's cached propagator; encoder(SLM field, complex) -> SLM phase.
    """

    def __init__(self, generator: nn.Module, encoder: nn.Module, setup: OpticalSetup) -> None:
        super().__init__()
        self.generator = generator
        self.encoder = encoder
        self.setup = setup

    def target_phase(self, amplitude: torch.Tensor) -> torch.Tensor:
        """The generator's phase at the target plane (B, 1, H, W); exposed for losses and inspection."""
        if amplitude.is_complex() or amplitude.dim() != 4 or amplitude.shape[1] != 1:
            raise ValueError(f"amplitude must be a real (B, 1, H, W) tensor, got {tuple(amplitude.shape)} "
                             f"{amplitude.dtype}")
        if tuple(amplitude.shape[-2:]) != self.setup.shape:
            raise ValueError(f"amplitude is {tuple(amplitude.shape[-2:])}, the SLM grid is {self.setup.shape}")
        return self.generator(amplitude)

    def forward(self, amplitude: torch.Tensor) -> torch.Tensor:
        phase = self.target_phase(amplitude)
        slm_field = self.setup.slm_propagator()(torch.polar(amplitude, phase))
        return self.encoder(slm_field)
