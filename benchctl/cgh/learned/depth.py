"""HoloNet for scenes with depth (`holonet3d`) and its divide-conquer-and-merge variants: the paper's future work.

Tensor Holography (Shi et al. 2021) reads an RGB-D scene and predicts the hologram at a plane in the middle of the
scene's depth; HoloNet (Peng et al. 2020) is a phase generator and a phase encoder around one propagation. The
network here is HoloNet's frame with the depth map as a second input of the phase generator:

- the phase generator reads (amplitude, depth) and predicts the phase at the middle plane of the bench's depth
  range, where the scene's light is spread least (every part of it is at most half the range out of focus there);
- amplitude * exp(i phase) is propagated from that plane to the SLM on the FULL grid (the paper's full-definition
  propagation, whatever the division);
- the phase encoder turns the SLM field into the SLM phase, as in HoloNet.

Divided by r (`holonet3d-dcm2`, `-dcm4`) both maps are pixel-unshuffled into r^2 sub-images each (2 r^2 channels:
the amplitude's, then the depth's), the same U-Nets run with r^2-scaled channels, the generator's r^2 phases are
pixel-shuffled back and the encoder's r^2 sub-holograms merged by the same LFMN as the 2D variants
(`holonet.holonet(..., inputs=2)`: one code path). The depth enters as (depth - middle) / (half the range), so
[-1, 1] across the range; the range is kept in the weights (`depth_range_nm`, exact integers), so a checkpoint
carries the range it was trained for. Without a depth map the network makes a flat scene at the setup's distance,
so a trained 3D network makes 2D targets too. Trained with the focal-stack loss (`benchctl.training`).
"""

from __future__ import annotations

import torch
from torch import nn

from benchctl.cgh.learned.dcm import PhaseHologramNet
from benchctl.optics.setup import OpticalSetup


class DepthHologramNet(PhaseHologramNet):
    """Target amplitude and depth (B, 1, H, W each; depth in metres from the SLM) -> SLM phase (B, 1, H, W).

    generator(amplitude, normalised depth) -> phase at the middle plane of `depth_range_m`; amplitude * exp(i phase)
    propagated middle plane -> SLM at full definition; encoder(SLM field) -> SLM phase. No depth range: the setup's
    distance is the whole range (a network for flat scenes)."""

    depth_range_nm: torch.Tensor

    def __init__(self, generator: nn.Module, encoder: nn.Module, setup: OpticalSetup,
                 depth_range_m: tuple[float, float] | None = None) -> None:
        super().__init__(generator, encoder, setup)
        near, far = depth_range_m if depth_range_m is not None else (setup.distance_m, setup.distance_m)
        if not 0 < near <= far:
            raise ValueError(f"a depth range must be (near, far) with 0 < near <= far metres, got {depth_range_m!r}")
        self.register_buffer("depth_range_nm", torch.tensor([round(near * 1e9), round(far * 1e9)]))
        self._range = (near, far)
        self.register_load_state_dict_post_hook(lambda module, _keys: module._read_range())

    def _read_range(self) -> None:
        near, far = (value * 1e-9 for value in self.depth_range_nm.tolist())
        self._range = (near, far)

    @property
    def depth_range_m(self) -> tuple[float, float]:
        """(near, far) in metres: the depth range this network was built (or trained) for."""
        return self._range

    @property
    def middle_m(self) -> float:
        """The plane the generator's phase belongs to: the middle of the depth range."""
        return (self._range[0] + self._range[1]) / 2

    def normalised_depth(self, depth_m: torch.Tensor) -> torch.Tensor:
        """(depth - middle) / (half the range): -1 .. 1 across the range (zero for a range of one plane)."""
        half = (self._range[1] - self._range[0]) / 2
        return (depth_m - self.middle_m) / half if half > 0 else torch.zeros_like(depth_m)

    def target_phase(self, amplitude: torch.Tensor, depth_m: torch.Tensor | None = None) -> torch.Tensor:
        """The generator's phase at the middle plane (B, 1, H, W); no `depth_m`: a flat scene at the setup's
        distance."""
        self.check(amplitude)
        if depth_m is None:
            depth_m = torch.full_like(amplitude, self.setup.distance_m)
        elif depth_m.shape != amplitude.shape or depth_m.is_complex():
            raise ValueError(f"depth must be a real map shaped like the amplitude {tuple(amplitude.shape)}, got "
                             f"{tuple(depth_m.shape)} {depth_m.dtype}")
        depth = self.normalised_depth(depth_m).to(amplitude.dtype)
        return self.generator(torch.cat([amplitude, depth], dim=1))

    def forward(self, amplitude: torch.Tensor, depth_m: torch.Tensor | None = None) -> torch.Tensor:
        phase = self.target_phase(amplitude, depth_m)
        middle = self.setup.at_distance(self.middle_m)
        return self.encoder(middle.slm_propagator()(torch.polar(amplitude, phase)))

    def extra_repr(self) -> str:
        near, far = self._range
        return f"depth range {near * 1e3:g} .. {far * 1e3:g} mm"
