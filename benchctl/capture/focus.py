"""Focus from captures: how sharp a frame is, where a through-focus sweep peaks, and the focus calibration's map
between a focus mechanism's steps and the depth its camera focuses at (docs/focus.md). numpy only: `benchctl focus go`
reads the map without torch.

Depth is the distance from the SLM along the optical axis (DESIGN.md); a depth in diopters is 1 / (that distance in
metres).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from benchctl.errors import BadValueError, BenchctlError

BIN = 4  # sensor pixels per side averaged before the sharpness is taken: read noise falls, a focused dot survives
FLOOR = 0.02  # the floor under which faint light is left out where frames of different powers compare
_DEPTH = re.compile(r"^\s*([-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)\s*(mm|m|D|dpt)\s*$")


def parse_depth(text: str) -> float:
    """'70mm', '70.5 mm', '0.07m', '14.3D', '14.3 dpt' -> depth from the SLM in metres (diopters: 1 / metres)."""
    match = _DEPTH.match(text)
    if not match:
        raise BadValueError(f"depth {text!r} not understood; give millimetres or diopters, e.g. 70mm or 14.3D")
    value, unit = float(match.group(1)), match.group(2)
    metres = value * 1e-3 if unit == "mm" else value if unit == "m" else (1 / value if value else math.inf)
    if not (0 < metres < math.inf):
        raise BadValueError(f"depth {text!r} is not a distance in front of the SLM (it must be > 0)")
    return metres


def sharpness(image: np.ndarray, floor: float = 0.0) -> float:
    """How concentrated the light of `image` (2-D, linear, dark subtracted) is: N sum(I^2) / sum(I)^2 over the image
    binned BIN x BIN, counting light above its median (the background) by more than `floor` of the brightest bin's.
    A point spread over A bins gives about N / A, so it peaks where the camera is focused on the dots or lines it
    sees. Without a floor, faint light near the noise counts more or less with the exposure; with FLOOR, frames
    taken at different powers compare (docs/focus.md)."""
    rows, cols = (n // BIN * BIN for n in image.shape[:2])
    if rows == 0 or cols == 0:
        raise BadValueError(f"an image of {image.shape[0]} x {image.shape[1]} pixels is too small to judge focus")
    binned = image[:rows, :cols].astype(np.float64).reshape(rows // BIN, BIN, cols // BIN, BIN).mean(axis=(1, 3))
    light = binned - np.median(binned)
    light = np.clip(light - floor * light.max(), 0, None)
    total = light.sum()
    return float(light.size * np.square(light).sum() / total**2) if total > 0 else 0.0


def fit_peak(steps: Sequence[float], values: Sequence[float]) -> float:
    """Where a through-focus sweep peaks: the vertex of the parabola fitted (least squares) to log(sharpness) over the
    points above the middle of the sweep's range around its best point (exact for a Gaussian peak; all of a fine
    sweep's points near focus), kept within them. BenchctlError when the best point is at an end of the sweep (the
    peak may lie outside it)."""
    x, y = np.asarray(steps, np.float64), np.asarray(values, np.float64)
    order = np.argsort(x)
    x, y = x[order], y[order]
    best = int(np.argmax(y))
    if best == 0 or best == len(x) - 1 or len(x) < 3:
        raise BenchctlError(f"the sharpest frame of the sweep is at its end ({x[best]:g} steps): the focus lies "
                            f"outside the swept range {x[0]:g} .. {x[-1]:g}; sweep wider")
    high = y >= (y.min() + y.max()) / 2
    low, top = best, best
    while low > 0 and high[low - 1]:
        low -= 1
    while top < len(x) - 1 and high[top + 1]:
        top += 1
    low, top = min(low, best - 1), max(top, best + 1)
    near = slice(low, top + 1)
    a, b, _ = np.polyfit(x[near] - x[best], np.log(np.maximum(y[near], 1e-300)), 2)
    vertex = x[best] - b / (2 * a) if a < 0 else x[best]
    return float(np.clip(vertex, x[low], x[top]))


@dataclass(frozen=True)
class FocusMap:
    """One colour's focus calibration: depth (mm from the SLM) = c0 + c1 s + c2 s^2 for a position s (steps from home)
    reached moving in direction `approach`; `backlash_steps` lost on a reversal, so a move that has to come back first
    goes `overshoot_steps` past (`Focus.move_to`); valid for `range_steps`."""

    coefficients: tuple[float, ...]
    approach: int
    backlash_steps: float
    repeatability_steps: float | None
    range_steps: tuple[float, float]
    residual_mm: float
    points: list[dict[str, float]] = field(default_factory=list)

    @property
    def overshoot_steps(self) -> int:
        """How far past a position a returning move goes: twice the backlash, at least 1 step."""
        return max(1, math.ceil(2 * abs(self.backlash_steps)))

    def depth_mm(self, steps: float) -> float:
        return float(np.polyval(self.coefficients[::-1], steps))

    def steps_for(self, depth_m: float) -> int:
        """The position (steps) that focuses at `depth_m`; BenchctlError outside the calibrated range."""
        target = depth_m * 1e3
        low, high = self.range_steps
        grid = np.linspace(low, high, 2049)
        depths = np.polyval(self.coefficients[::-1], grid)
        if not (min(depths) <= target <= max(depths)):
            raise BenchctlError(f"depth {target:g} mm is outside what the focus calibration covers "
                                f"({min(depths):.4g} .. {max(depths):.4g} mm)")
        crossings = np.nonzero(np.diff(np.sign(depths - target)))[0]
        i = int(crossings[0]) if len(crossings) else int(np.argmin(abs(depths - target)))
        j = min(i + 1, len(grid) - 1)
        span = depths[j] - depths[i]
        s = grid[i] + (target - depths[i]) / span * (grid[j] - grid[i]) if span else grid[i]
        return round(float(s))

    @classmethod
    def fit(cls, points: Sequence[tuple[float, float]], *, approach: int, backlash_steps: float,
            repeatability_steps: float | None, range_steps: tuple[float, float]) -> FocusMap:
        """The map through (steps, depth mm) peaks: a straight line through three, a parabola through four or more
        (so that the residual always has a degree of freedom to show a misfit)."""
        if len(points) < 3:
            raise BenchctlError("a focus calibration needs peaks at three depths at least")
        s, z = (np.array(v, np.float64) for v in zip(*points))
        degree = 1 if len(points) == 3 else 2
        coefficients = np.polyfit(s, z, degree)[::-1]
        residual = float(np.sqrt(np.mean(np.square(np.polyval(coefficients[::-1], s) - z))))
        return cls(tuple(float(c) for c in coefficients), approach, backlash_steps, repeatability_steps,
                   range_steps, residual, [{"steps": float(a), "depth_mm": float(b)} for a, b in points])

    def to_dict(self) -> dict[str, Any]:
        return {"coefficients": list(self.coefficients), "approach": self.approach,
                "backlash_steps": self.backlash_steps, "overshoot_steps": self.overshoot_steps,
                "repeatability_steps": self.repeatability_steps, "range_steps": list(self.range_steps),
                "residual_mm": self.residual_mm, "points": self.points}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> FocusMap:
        return cls(tuple(data["coefficients"]), int(data["approach"]), float(data["backlash_steps"]),
                   data.get("repeatability_steps"), (float(data["range_steps"][0]), float(data["range_steps"][1])),
                   float(data["residual_mm"]), list(data.get("points", [])))
