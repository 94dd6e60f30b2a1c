"""Divide-conquer-and-merge (DCM): the frame every learned method here shares, classical or divided.

A learned hologram network is two sub-networks around one propagation (`PhaseHologramNet`):
the phase generator turns the target amplitude into a phase at the target plane; amplitude * exp(i phase)
is propagated to the SLM (-z) on the FULL grid; the phase encoder turns that SLM field into the SLM phase.

DCM (`Divided`) wraps each sub-network: PixelUnshuffle(r) splits the input into r^2 sub-images of
H/r x W/r, the sub-network runs on those (channels r^2 for the generator, 2 r^2 for HoloNet's encoder),
and a merger puts the result back at full definition: PixelShuffle(r) for the generator, the LFMN
super-resolution network (or the pyramid of LFMNs) for the encoder. With r = 1 and PixelShuffle(1) the same
wrapper is the classical network, so baselines and DCM variants run one code path.

Only the sub-networks see low definition: the propagation runs on the full SLM grid. `LowDefinitionNet` is
the paper's ablation that does not: each complex sub-hologram is propagated on its own at low definition,
pitch p r (the paper: PSNR drops to 16.6 dB at x2).

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

    def check(self, amplitude: torch.Tensor) -> None:
        """ValueError unless `amplitude` is a real (B, 1, H, W) tensor on the setup's SLM grid."""
        if amplitude.is_complex() or amplitude.dim() != 4 or amplitude.shape[1] != 1:
            raise ValueError(f"amplitude must be a real (B, 1, H, W) tensor, got {tuple(amplitude.shape)} "
                             f"{amplitude.dtype}")
        if tuple(amplitude.shape[-2:]) != self.setup.shape:
            raise ValueError(f"amplitude is {tuple(amplitude.shape[-2:])}, the SLM grid is {self.setup.shape}")

    def target_phase(self, amplitude: torch.Tensor) -> torch.Tensor:
        """The generator's phase at the target plane (B, 1, H, W); exposed for losses and inspection."""
        self.check(amplitude)
        return self.generator(amplitude)

    def forward(self, amplitude: torch.Tensor) -> torch.Tensor:
        phase = self.target_phase(amplitude)
        slm_field = self.setup.slm_propagator()(torch.polar(amplitude, phase))
        return self.encoder(slm_field)


def low_definition_setup(setup: OpticalSetup, factor: int) -> OpticalSetup:
    """The setup one sub-image of a `factor` x `factor` unshuffle sees at low definition: grid and ROI divided
    by r (rounded up), pitch multiplied by r (the image keeps its physical size), the same distance and
    wavelength, and the iris at the same physical frequency (r times its fraction of the coarser Nyquist)."""
    (h, w), (rh, rw) = setup.shape, setup.roi
    return OpticalSetup(wavelength_m=setup.wavelength_m, pitch_m=(setup.pitch_m[0] * factor, setup.pitch_m[1] * factor),
                        distance_m=setup.distance_m, shape=(-(-h // factor), -(-w // factor)),
                        roi=(max(1, rh // factor), max(1, rw // factor)), padding=setup.padding,
                        aperture=None if setup.aperture is None else setup.aperture * factor)


class LowDefinitionNet(PhaseHologramNet):
    """The paper's "ASM at low definition" ablation: the generator's r^2 complex sub-images are propagated to
    the SLM one by one on the low-definition grid (pitch p r), not merged and propagated at full definition;
    the encoder's sub-network reads those r^2 SLM sub-fields and its merger merges its r^2 outputs."""

    generator: Divided
    encoder: Divided

    def __init__(self, generator: Divided, encoder: Divided, setup: OpticalSetup) -> None:
        super().__init__(generator, encoder, setup)
        if generator.factor < 2 or encoder.factor != generator.factor:
            raise ValueError(f"low-definition propagation needs one DCM factor >= 2 for both sub-networks, got "
                             f"{generator.factor} and {encoder.factor}")
        self.low_setup = low_definition_setup(setup, generator.factor)

    def forward(self, amplitude: torch.Tensor) -> torch.Tensor:
        self.check(amplitude)
        r = self.generator.factor
        sub_amplitudes = F.pixel_unshuffle(pad_to_multiple(amplitude, r), r)
        sub_fields = torch.polar(sub_amplitudes, self.generator.subnet(sub_amplitudes))
        slm_fields = self.low_setup.slm_propagator()(sub_fields)
        h, w = amplitude.shape[-2:]
        return self.encoder.merge(self.encoder.subnet(slm_fields))[..., :h, :w]
