"""Peak memory of a procedure, estimated from its parameters before it starts, against the machine's memory.

Counts that scale memory get their upper bound from the estimate, not from a constant: `frames` and `dark_frames`
(an exposure holds every RAW file it captures until it has them all; decoding then averages them as they come, one
at a time), model calibration's `patterns` (the fit propagates every pattern at once, with gradients) and `fit_steps`
(every step's loss is kept). A count whose estimate does not fit is refused with one line that names it, the
estimate, the limit and the largest count that fits. The figures per pixel were measured (peak RSS, docs/memory.md)
and are rounded up. The limit is $BENCHCTL_MAX_MEMORY (bytes, or 512M, 8G, ...), else the machine's physical memory.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from benchctl.devices.camera import frame_size
from benchctl.errors import BadValueError
from benchctl.optics.plan import plan_propagation
from benchctl.profiles import Profile

MAX_MEMORY_ENV = "BENCHCTL_MAX_MEMORY"
INTERPRETER_BYTES = 250 * 2**20  # Python, numpy, torch and benchctl imported (README: Bounded input)
# One exposure, per pixel of the RAW frame (margins included): the simulated camera's rendering, the decode and the
# running mean (constant in the count), and each RAW file held until the exposure has all its frames (16 bit).
EXPOSURE_BYTES_PER_PX = 32
RAW_BYTES_PER_PX = 2.2
# Model calibration's fit, per pixel of the padded propagation grid: the Zernike basis, transfer functions and
# optimiser (constant), and per pattern its fields and their gradients through the propagation.
FIT_BYTES_PER_PADDED_PX = 160
FIT_BYTES_PER_PATTERN_PX = 36
FIT_BYTES_PER_STEP = 200  # each step's loss: in the fit, its step result and the report's plot
_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def memory_limit() -> int | None:
    """The memory a procedure may plan to use: $BENCHCTL_MAX_MEMORY, else this machine's physical memory (None where
    the system does not say)."""
    text = os.environ.get(MAX_MEMORY_ENV, "").strip()
    if text:
        match = re.fullmatch(r"(\d+(?:\.\d+)?)\s*([KMGT]?)(?:i?B)?", text, re.IGNORECASE)
        if match is None or float(match[1]) <= 0:
            raise BadValueError(f"${MAX_MEMORY_ENV} must be a size such as 8G, 512M or a number of bytes, got {text!r}")
        return int(float(match[1]) * _UNITS[match[2].upper()])
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):  # no sysconf (Windows) or no such name
        return None


def size_text(count: float) -> str:
    """Bytes for people: '1.2 GB', '37 MB' (decimal units)."""
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if count >= scale:
            return f"{count / scale:.3g} {unit}"
    return f"{count / 1e3:.3g} kB"


@dataclass(frozen=True)
class Estimate:
    """The peak of one kind of step: fixed bytes plus bytes per unit of each count, and what it is for people."""

    what: str
    fixed: float
    per: dict[str, float]  # parameter -> bytes per unit
    counts: dict[str, int]

    @property
    def peak(self) -> float:
        return INTERPRETER_BYTES + self.fixed + sum(self.per[key] * self.counts[key] for key in self.per)

    def largest(self, key: str, limit: int) -> int:
        """The largest value of `key` whose peak fits in `limit` bytes, the other counts as they are."""
        rest = self.peak - self.per[key] * self.counts[key]
        return max(0, math.floor((limit - rest) / self.per[key]))


def exposure_estimate(profile: Profile, frames: int, dark_frames: int) -> Estimate:
    """An exposure step: `frames` lit and `dark_frames` dark RAW frames of the camera's size (its driver's
    `frame_size`: a GenICam camera's region, the simulated camera's [sim.sensor], by default an EOS M10's)."""
    frame = frame_size(profile)
    rows, cols = frame.rows, frame.cols
    raw = RAW_BYTES_PER_PX * rows * cols
    return Estimate(f"an exposure of RAW frames of {cols} x {rows} px ({size_text(raw)} held per frame)",
                    EXPOSURE_BYTES_PER_PX * rows * cols, {"frames": raw, "dark_frames": raw},
                    {"frames": frames, "dark_frames": dark_frames})


def fit_estimate(profile: Profile, patterns: int, flat: bool, fit_steps: int, planes: int = 1) -> Estimate:
    """Model calibration's fit of `patterns` captured patterns (and the `flat` one) over `fit_steps` steps, on the
    largest padded grid of the profile's channels; captured at `planes` focus depths, each pattern's fields and
    gradients are propagated to every one of them (the per-pattern bytes times the planes, not measured apart)."""
    profile.require("slm", "optics", "laser")
    slm, optics = profile.section("slm"), profile.section("optics")
    padded = max(math.prod(plan_propagation(slm.shape, optics.distance_m, channel.wavelength_m, slm.pitch_m,
                                            aperture=optics.iris_fraction).padded_shape)
                 for channel in profile.channels)
    return Estimate(f"the model fit on a padded grid of {padded / 1e6:.3g} Mpx",
                    (FIT_BYTES_PER_PADDED_PX + FIT_BYTES_PER_PATTERN_PX * planes * flat) * padded,
                    {"patterns": FIT_BYTES_PER_PATTERN_PX * planes * padded, "fit_steps": FIT_BYTES_PER_STEP},
                    {"patterns": patterns, "fit_steps": fit_steps})


# One training step (forward, propagation, ROI loss, backward, Adam; batch 1) per grid pixel: per network, the largest
# per pixel that `benchctl bench learned --grids` measured on the paper's grids (at 1088 x 1920 for all of them,
# where fixed costs weigh most; docs/reproduction.md, "What fits in 24 GiB"). A method not measured takes the
# measured network of its family and DCM factor.
TRAINING_BYTES_PER_PX = {"holonet": 4323, "holonet-dcm2": 2511, "holonet-dcm4": 921, "holonet-pyramid": 2860,
                         "ccnn": 526, "ccnn-dcm4": 490}
MEASURED_AS = {("holonet", 1): "holonet", ("holonet", 2): "holonet-dcm2", ("holonet", 4): "holonet-dcm4",
               ("ccnn", 1): "ccnn", ("ccnn", 4): "ccnn-dcm4"}


def training_estimate(method: str, family: str, factor: int, grid: tuple[int, int], batch_size: int) -> Estimate:
    """One training step of `method` (of network `family` with DCM `factor`) on `grid` with `batch_size` images."""
    measured = method if method in TRAINING_BYTES_PER_PX else MEASURED_AS[(family, factor)]
    return Estimate(f"one training step of {method} on {grid[0]} x {grid[1]}", 0.0,
                    {"batch_size": TRAINING_BYTES_PER_PX[measured] * grid[0] * grid[1]}, {"batch_size": batch_size})


def check_training_memory(estimate: Estimate) -> None:
    """BadValueError (one line: the estimate, the limit, the largest batch that fits) when a training step cannot
    fit in the memory limit."""
    limit = memory_limit()
    if limit is not None and estimate.peak > limit:
        largest = estimate.largest("batch_size", limit)
        raise BadValueError(f"{estimate.what} with --batch-size {estimate.counts['batch_size']} needs about "
                            f"{size_text(estimate.peak)}, above the {size_text(limit)} of memory here: "
                            + (f"at most --batch-size {largest} fits" if largest >= 1 else
                               "use a smaller --size or a DCM variant") + f" (${MAX_MEMORY_ENV} sets the limit)")


ESTIMATES: dict[str, Callable[[Profile, Any], Estimate]] = {
    "frames": lambda profile, params: exposure_estimate(profile, params.frames, getattr(params, "dark_frames", 0)),
    "patterns": lambda profile, params: fit_estimate(profile, params.patterns, getattr(params, "flat", False),
                                                     getattr(params, "fit_steps", 0),
                                                     max(1, len(getattr(params, "focus_depths_mm", ())))),
}


def check_memory(profile: Profile, params: Any, where: str) -> list[str]:
    """The peak memory of a procedure with parameters `params` on `profile`, for a dry run (one line per kind of
    step that scales with a count); a BadValueError naming `where` and the count when it does not fit the limit."""
    limit = memory_limit()
    lines = []
    for name, estimate_of in ESTIMATES.items():
        if not isinstance(getattr(params, name, None), int):  # a Python procedure may use the name for another thing
            continue
        estimate = estimate_of(profile, params)
        if limit is not None and estimate.peak > limit:
            key = max(estimate.per, key=lambda k: estimate.per[k] * estimate.counts[k])
            others = ", ".join(f"{k} = {v}" for k, v in estimate.counts.items() if k != key)
            largest = estimate.largest(key, limit)
            raise BadValueError(
                f"{where}: {key} = {estimate.counts[key]} (with {others}) needs about {size_text(estimate.peak)} at "
                f"the peak of {estimate.what}, above the {size_text(limit)} of memory here: "
                + (f"at most {key} = {largest}" if largest >= 1 else f"not even {key} = 1 fits")
                + f" (${MAX_MEMORY_ENV} sets the limit)")
        lines.append(f"memory: about {size_text(estimate.peak)} at the peak of {estimate.what}"
                     + (f"; limit {size_text(limit)}" if limit is not None else ""))
    return lines
