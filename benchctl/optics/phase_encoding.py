"""The one mapping between phase (radians) and SLM gray levels, through a per-wavelength lookup table.

A real SLM's phase response depends on the wavelength and is measured, so the table is data: 2^bit_depth
phases, one per gray level, non-decreasing, spanning more or less than 2 pi. Encoding picks, for each pixel,
the gray level whose phase is nearest modulo 2 pi. It goes through a precomputed inverse table over a fine
phase grid, so encoding costs one lookup per pixel and a 1088 x 1920 hologram needs no per-level work.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

TWO_PI = 2.0 * math.pi
_MAX_BIT_DEPTH = 16


class PhaseLUT:
    """Gray level -> phase table of one SLM at one wavelength, with its precomputed inverse."""

    def __init__(self, phases: torch.Tensor | Sequence[float]) -> None:
        """phases[g] is the phase in radians that gray level g shows; 2^bit_depth entries, non-decreasing."""
        table = torch.as_tensor(phases, dtype=torch.float64).flatten().clone()
        levels = table.numel()
        bit_depth = levels.bit_length() - 1
        if levels < 2 or levels != 1 << bit_depth or bit_depth > _MAX_BIT_DEPTH:
            raise ValueError(
                f"a phase table needs 2^bit_depth entries (bit depth 1..{_MAX_BIT_DEPTH}), got {levels}"
            )
        if not torch.isfinite(table).all():
            raise ValueError("phase table contains NaN or infinite values")
        steps = table.diff()
        if (steps < 0).any():
            g = int(torch.nonzero(steps < 0)[0])
            raise ValueError(
                f"phase table must be non-decreasing: gray {g + 1} has {table[g + 1]:.6g} rad "
                f"after {table[g]:.6g} rad at gray {g}"
            )
        self.phases = table
        self.bit_depth = bit_depth
        self.dtype = torch.uint8 if bit_depth <= 8 else torch.int32
        # At least 16 inverse bins per gray level; for linear tables with 2^bit_depth levels per 2 pi the
        # decision boundaries then fall on bin edges and encoding is exact to half a gray step.
        self.bins = 1 << max(16, bit_depth + 4)
        self.inverse = self._nearest_levels()

    @classmethod
    def linear(cls, bit_depth: int = 8, two_pi_gray: float | None = None) -> PhaseLUT:
        """Ideal table phase = 2 pi g / two_pi_gray; the default 2^bit_depth covers [0, 2 pi) exactly."""
        levels = 1 << bit_depth
        period = float(levels if two_pi_gray is None else two_pi_gray)
        if not period > 0:
            raise ValueError(f"two_pi_gray must be > 0, got {two_pi_gray!r}")
        return cls(torch.arange(levels, dtype=torch.float64) * (TWO_PI / period))

    @property
    def levels(self) -> int:
        """Number of gray levels, 2^bit_depth."""
        return self.phases.numel()

    def _nearest_levels(self) -> torch.Tensor:
        """For each bin centre of a fine grid over [0, 2 pi), the gray level nearest in phase modulo 2 pi.

        Only the levels of the table's first 2 pi period are used: past it the table repeats phases, and
        mixing levels from two periods would make neighbouring pixels of a smooth phase jump across the range.
        """
        candidates = torch.nonzero(self.phases < self.phases[0] + TWO_PI).flatten()
        wrapped = torch.remainder(self.phases[candidates], TWO_PI)
        by_phase = torch.argsort(wrapped, stable=True)
        order, ring = candidates[by_phase], wrapped[by_phase]
        centres = (torch.arange(self.bins, dtype=torch.float64) + 0.5) * (TWO_PI / self.bins)
        above = torch.searchsorted(ring, centres)
        below = above - 1  # -1 wraps to the largest phase, one turn lower
        above = above % ring.numel()  # past the end wraps to the smallest phase, one turn higher
        dist_below = torch.remainder(centres - ring[below], TWO_PI)
        dist_above = torch.remainder(ring[above] - centres, TWO_PI)
        nearest = torch.where(dist_below <= dist_above, order[below], order[above])
        return nearest.to(self.dtype)

    def __repr__(self) -> str:
        return (
            f"PhaseLUT({self.levels} levels, {self.phases[0]:.4g}..{self.phases[-1]:.4g} rad "
            f"= {(self.phases[-1] - self.phases[0]) / math.pi:.3g} pi)"
        )


def phase_to_gray(phase: torch.Tensor, lut: PhaseLUT) -> torch.Tensor:
    """Gray levels (uint8, or int32 above 8 bit) whose table phase is nearest each phase modulo 2 pi."""
    position = torch.floor(phase.detach().to(torch.float64) * (lut.bins / TWO_PI)).long()
    return lut.inverse.to(phase.device)[torch.remainder(position, lut.bins)]


def gray_to_phase(gray: torch.Tensor, lut: PhaseLUT) -> torch.Tensor:
    """Phase in radians (float32) that each gray level shows, by table lookup."""
    if gray.is_floating_point() or gray.is_complex() or gray.dtype == torch.bool:
        raise ValueError(f"gray levels must be an integer tensor, got {gray.dtype}")
    index = gray.long()
    if index.numel() and (index.min() < 0 or index.max() >= lut.levels):
        raise ValueError(
            f"gray levels must lie in 0..{lut.levels - 1}, got {int(index.min())}..{int(index.max())}"
        )
    return lut.phases.to(device=gray.device, dtype=torch.float32)[index]
