"""The one mapping between phase (radians) and SLM gray levels, through a per-wavelength lookup table.

A real SLM's phase response depends on the wavelength and is measured, so the table is data: 2^bit_depth
phases, one per gray level, non-decreasing, spanning more or less than 2 pi. Encoding picks, for each pixel,
the gray level whose phase is nearest modulo 2 pi. It goes through a precomputed inverse table over a fine
phase grid, so encoding costs one lookup per pixel and a 1088 x 1920 hologram needs no per-level work.

Numpy, not torch: gray frames are numpy arrays, and SLM commands that show a phase file must not load torch.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

TWO_PI = 2.0 * math.pi
_MAX_BIT_DEPTH = 16


class PhaseLUT:
    """Gray level -> phase table of one SLM at one wavelength, with its precomputed inverse (both read-only)."""

    def __init__(self, phases: ArrayLike) -> None:
        """phases[g] is the phase in radians that gray level g shows; 2^bit_depth entries, non-decreasing."""
        table = np.array(phases, dtype=np.float64).ravel()
        levels = table.size
        bit_depth = levels.bit_length() - 1
        if levels < 2 or levels != 1 << bit_depth or bit_depth > _MAX_BIT_DEPTH:
            raise ValueError(
                f"a phase table needs 2^bit_depth entries (bit depth 1..{_MAX_BIT_DEPTH}), got {levels}"
            )
        if not np.isfinite(table).all():
            raise ValueError("phase table contains NaN or infinite values")
        drops = np.flatnonzero(np.diff(table) < 0)
        if drops.size:
            g = int(drops[0])
            raise ValueError(
                f"phase table must be non-decreasing: gray {g + 1} has {table[g + 1]:.6g} rad "
                f"after {table[g]:.6g} rad at gray {g}"
            )
        table.flags.writeable = False  # tables are shared (cached per channel and wavelength)
        self.phases = table
        self.bit_depth = bit_depth
        self.dtype = np.dtype(np.uint8 if bit_depth <= 8 else np.int32)
        # At least 16 inverse bins per gray level; for linear tables with 2^bit_depth levels per 2 pi the
        # decision boundaries then fall on bin edges and encoding is exact to half a gray step.
        self.bins = 1 << max(16, bit_depth + 4)
        self.inverse = self._nearest_levels()
        self.inverse.flags.writeable = False

    @classmethod
    def linear(cls, bit_depth: int = 8, two_pi_gray: float | None = None) -> PhaseLUT:
        """Ideal table phase = 2 pi g / two_pi_gray; the default 2^bit_depth covers [0, 2 pi) exactly."""
        levels = 1 << bit_depth
        period = float(levels if two_pi_gray is None else two_pi_gray)
        if not period > 0:
            raise ValueError(f"two_pi_gray must be > 0, got {two_pi_gray!r}")
        return cls(np.arange(levels, dtype=np.float64) * (TWO_PI / period))

    @property
    def levels(self) -> int:
        """Number of gray levels, 2^bit_depth."""
        return self.phases.size

    @property
    def widest_gap(self) -> float:
        """The widest phase interval (radians, modulo 2 pi) that no gray level shows: one gray step for an
        ideal table, the missing stroke for a panel whose levels span less than 2 pi at this wavelength."""
        ring = np.sort(np.remainder(self.phases[self.phases < self.phases[0] + TWO_PI], TWO_PI))
        return float(np.diff(ring, append=ring[0] + TWO_PI).max())

    def _nearest_levels(self) -> np.ndarray:
        """For each bin centre of a fine grid over [0, 2 pi), the gray level nearest in phase modulo 2 pi.

        Only the levels of the table's first 2 pi period are used: past it the table repeats phases, and
        mixing levels from two periods would make neighbouring pixels of a smooth phase jump across the range.
        """
        candidates = np.flatnonzero(self.phases < self.phases[0] + TWO_PI)
        wrapped = np.remainder(self.phases[candidates], TWO_PI)
        by_phase = np.argsort(wrapped, kind="stable")
        order, ring = candidates[by_phase], wrapped[by_phase]
        centres = (np.arange(self.bins, dtype=np.float64) + 0.5) * (TWO_PI / self.bins)
        above = np.searchsorted(ring, centres)
        below = above - 1  # -1 wraps to the largest phase, one turn lower
        above = above % ring.size  # past the end wraps to the smallest phase, one turn higher
        dist_below = np.remainder(centres - ring[below], TWO_PI)
        dist_above = np.remainder(ring[above] - centres, TWO_PI)
        nearest = np.where(dist_below <= dist_above, order[below], order[above])
        return nearest.astype(self.dtype)

    def __repr__(self) -> str:
        return (
            f"PhaseLUT({self.levels} levels, {self.phases[0]:.4g}..{self.phases[-1]:.4g} rad "
            f"= {(self.phases[-1] - self.phases[0]) / math.pi:.3g} pi)"
        )


def phase_to_gray(phase: ArrayLike, lut: PhaseLUT) -> np.ndarray:
    """Gray levels (uint8, or int32 above 8 bit) whose table phase is nearest each phase modulo 2 pi."""
    position = np.floor(np.asarray(phase, dtype=np.float64) * (lut.bins / TWO_PI)).astype(np.int64)
    return lut.inverse[np.remainder(position, lut.bins)]


def gray_to_phase(gray: ArrayLike, lut: PhaseLUT) -> np.ndarray:
    """Phase in radians (float32) that each gray level shows, by table lookup."""
    gray = np.asarray(gray)
    if gray.dtype.kind not in "iu":
        raise ValueError(f"gray levels must be an integer array, got {gray.dtype}")
    if gray.size:
        low, high = int(gray.min()), int(gray.max())
        if low < 0 or high >= lut.levels:
            raise ValueError(f"gray levels must lie in 0..{lut.levels - 1}, got {low}..{high}")
    return lut.phases[gray].astype(np.float32)
