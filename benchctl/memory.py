"""Peak memory of a procedure, estimated from its parameters before it starts, against the memory it may use.

A run's peak is that of its largest kind of step, on top of what every run holds (the interpreter, torch and the
runner, and the optical setups later steps keep: transfer functions and targets, per colour): an exposure (the
simulated camera's rendering; every RAW file it captures is held until it has them all), the decoding and
registration of an exposure (in the step that reads it: a CITL iteration, a colour capture's processing), a
hologram (one colour's DPAC or SGD, or a CITL gradient step, on the padded grid) and model calibration's fit. Counts
that scale memory get their upper bound from the estimate, not from a constant: `frames` and `dark_frames`, model
calibration's `patterns` (the fit propagates every pattern at once, with gradients) and `fit_steps` (every step's
loss is kept). A count whose estimate does not fit is refused with one line that names it, the estimate, the limit
and the largest count that fits; a run whose fixed part does not fit is refused too. The figures per pixel were
measured (peak RSS of whole runs and of each kind alone, docs/memory.md) and are rounded up.

The limit is $BENCHCTL_MAX_MEMORY (bytes, or 512M, 8G, ...), else what this process may grow to now: its own
resident memory plus the memory available to it (the kernel's MemAvailable, or less where a cgroup
limit leaves less room: v2 memory.max - memory.current, v1 memory.limit_in_bytes - memory.usage_in_bytes, reclaimable
file cache not counted as used), less a margin for the other processes that grow meanwhile. Comparing with the
machine's total memory accepted a 19.3 GB training run on a machine whose other jobs left less.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchctl.devices.camera import frame_size
from benchctl.errors import BadValueError
from benchctl.optics.metrics import centred_slices
from benchctl.optics.plan import plan_propagation, window_plan
from benchctl.optics.planes import MAX_PLANES
from benchctl.profiles import Profile

MAX_MEMORY_ENV = "BENCHCTL_MAX_MEMORY"
# Of the memory available now, this fraction (at least MARGIN_BYTES) is left to the machine's other processes.
MARGIN_FRACTION = 0.1
MARGIN_BYTES = 256 * 2**20
PROC = Path("/proc")  # where the kernel says what is available (tests point these at fake trees)
CGROUP_ROOT = Path("/sys/fs/cgroup")
UNLIMITED = 2**60  # a cgroup v1 limit this large is none (the kernel writes 2^63 rounded down to a page)
INTERPRETER_BYTES = 250 * 2**20  # Python, numpy, torch and benchctl imported (README: Bounded input)
# What every run holds on top: torch's and the runner's working state, the run record and the report.
RUN_BYTES = 160 * 2**20
# Per pixel of the padded propagation grid and per colour the run uses: the optical setups later steps keep.
RETAINED_BYTES_PER_PADDED_PX = 32
# One exposure, per pixel of the RAW frame (margins included): the simulated camera's rendering (constant in the
# count), and each RAW file held until the exposure has all its frames (16 bit).
EXPOSURE_BYTES_PER_PX = 40
RAW_BYTES_PER_PX = 2.2
# Decoding, registering and scoring one exposure, per pixel of its RAW frame (frames are averaged as decoded).
DECODE_BYTES_PER_PX = 56
# One colour's hologram (DPAC, SGD; a CITL gradient step), per pixel of the padded propagation grid.
HOLOGRAM_BYTES_PER_PADDED_PX = 130
# Model calibration's fit, per pixel of the padded propagation grid: the Zernike basis, transfer functions and
# optimiser (constant), and per pattern its fields and their gradients through the propagation.
FIT_BYTES_PER_PADDED_PX = 160
FIT_BYTES_PER_PATTERN_PX = 36
FIT_BYTES_PER_STEP = 200  # each step's loss: in the fit, its step result and the report's plot
# A hologram of a scene with depth, on top of a hologram's: per depth whose transfer function its optimiser holds (a
# sweep's depths, else its planes), one complex64 grid the size of the ROI's propagation grid; per plane scored at
# once, the ROI's fields, amplitudes, masks and their gradients (measured about 38 B per ROI pixel).
TRANSFER_BYTES_PER_ROI_GRID_PX = 8
PLANE_BYTES_PER_ROI_PX = 40
_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def memory_limit() -> int | None:
    """The memory a procedure may plan to use: $BENCHCTL_MAX_MEMORY, else this process's resident memory plus what is
    available to it less a margin (`available_memory`; None where the system does not say)."""
    text = os.environ.get(MAX_MEMORY_ENV, "").strip()
    if text:
        match = re.fullmatch(r"(\d+(?:\.\d+)?)\s*([KMGT]?)(?:i?B)?", text, re.IGNORECASE)
        if match is None or float(match[1]) <= 0:
            raise BadValueError(f"${MAX_MEMORY_ENV} must be a size such as 8G, 512M or a number of bytes, got {text!r}")
        return int(float(match[1]) * _UNITS[match[2].upper()])
    available = available_memory()
    if available is None:
        return None
    return _resident() + max(0, available - max(int(MARGIN_FRACTION * available), MARGIN_BYTES))


def limit_words() -> str:
    """What `memory_limit` is, for the line that names it."""
    return "of memory here" if os.environ.get(MAX_MEMORY_ENV, "").strip() else "this process may grow to now"


def available_memory() -> int | None:
    """Bytes this process can still allocate: the kernel's MemAvailable, or the room its cgroups leave if less (None
    where neither is known: not Linux)."""
    rooms = [room for room in (_meminfo_available(), _cgroup_room()) if room is not None]
    return min(rooms) if rooms else None


def _meminfo_available() -> int | None:
    try:
        text = (PROC / "meminfo").read_text()
    except OSError:
        return None
    match = re.search(r"^MemAvailable:\s+(\d+) kB$", text, re.MULTILINE)
    return int(match[1]) * 1024 if match else None


def _resident() -> int:
    """This process's resident memory now (0 where /proc does not say)."""
    try:
        return int((PROC / "self" / "statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def _cgroup_room() -> int | None:
    """The least room any memory limit of this process's cgroups (and their ancestors) leaves: limit minus usage,
    the usage without its inactive file cache (the kernel reclaims it before it refuses memory). None without a
    limit."""
    try:
        lines = (PROC / "self" / "cgroup").read_text().splitlines()
    except OSError:
        return None
    rooms = []
    for line in lines:
        _, controllers, path = line.split(":", 2)
        if controllers == "":  # cgroup v2
            base = CGROUP_ROOT if (CGROUP_ROOT / "cgroup.controllers").is_file() else CGROUP_ROOT / "unified"
            files = ("memory.max", "memory.current", "inactive_file")
        elif "memory" in controllers.split(","):  # cgroup v1
            base, files = CGROUP_ROOT / "memory", ("memory.limit_in_bytes", "memory.usage_in_bytes",
                                                  "total_inactive_file")
        else:
            continue
        folder = base / path.lstrip("/")
        if not folder.is_dir():  # a cgroup namespace: this process sees its own cgroup as the root
            folder = base
        while True:
            room = _room(folder, *files)
            if room is not None:
                rooms.append(room)
            if folder == base or base not in folder.parents:
                break
            folder = folder.parent
    return min(rooms) if rooms else None


def _room(folder: Path, limit_file: str, usage_file: str, inactive_key: str) -> int | None:
    try:
        limit_text = (folder / limit_file).read_text().strip()
        usage = int((folder / usage_file).read_text())
    except (OSError, ValueError):
        return None
    if limit_text == "max" or int(limit_text) >= UNLIMITED:
        return None
    try:
        stat = dict(line.split() for line in (folder / "memory.stat").read_text().splitlines())
        usage -= int(stat.get(inactive_key, 0))
    except (OSError, ValueError):
        pass
    return max(0, int(limit_text) - usage)


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


def padded_pixels(profile: Profile) -> int:
    """The largest padded propagation grid of the profile's channels, in pixels (0 without an SLM and optics)."""
    if profile.slm is None or profile.optics is None or not profile.channels:
        return 0
    slm, optics = profile.slm, profile.optics
    return max(math.prod(plan_propagation(slm.shape, optics.distance_m, channel.wavelength_m, slm.pitch_m,
                                          aperture=optics.iris_fraction).padded_shape)
               for channel in profile.channels)


def roi_grid_pixels(profile: Profile) -> int:
    """The largest grid, in pixels, on which the profile's channels propagate to the ROI alone (`window_plan`: what
    focal stacks use)."""
    slm, optics = profile.section("slm"), profile.section("optics")
    rows, cols = centred_slices(slm.shape, optics.roi)
    window = (rows.start, optics.roi[0], cols.start, optics.roi[1])
    return max(math.prod(window_plan(plan_propagation(slm.shape, optics.distance_m, channel.wavelength_m,
                                                      slm.pitch_m, aperture=optics.iris_fraction),
                                     window).padded_shape)
               for channel in profile.channels)


def run_bytes(profile: Profile, colours: int) -> float:
    """What every run on `profile` holds beside the interpreter, with `colours` laser colours in use."""
    return RUN_BYTES + RETAINED_BYTES_PER_PADDED_PX * padded_pixels(profile) * colours


def _raw_pixels(profile: Profile) -> tuple[int, int]:
    """(rows, cols) of the camera's RAW frame, as its driver gives it (`frame_size`: a GenICam camera's region, the
    simulated camera's [sim.sensor], by default an EOS M10's 5280 x 3528)."""
    frame = frame_size(profile)
    return frame.rows, frame.cols


def exposure_estimate(profile: Profile, frames: int, dark_frames: int, colours: int = 1) -> Estimate:
    """An exposure step: `frames` lit and `dark_frames` dark RAW frames of the camera's sensor."""
    rows, cols = _raw_pixels(profile)
    raw = RAW_BYTES_PER_PX * rows * cols
    return Estimate(f"an exposure of RAW frames of {cols} x {rows} px ({size_text(raw)} held per frame)",
                    run_bytes(profile, colours) + EXPOSURE_BYTES_PER_PX * rows * cols,
                    {"frames": raw, "dark_frames": raw}, {"frames": frames, "dark_frames": dark_frames})


def decode_estimate(profile: Profile, colours: int = 1) -> Estimate:
    """Decoding, registering and scoring an exposure's RAW frames (one at a time)."""
    rows, cols = _raw_pixels(profile)
    return Estimate(f"decoding and registering RAW frames of {cols} x {rows} px",
                    run_bytes(profile, colours) + DECODE_BYTES_PER_PX * rows * cols, {}, {})


def hologram_estimate(profile: Profile, colours: int = 1) -> Estimate:
    """One colour's hologram (or a CITL gradient step) on the largest padded grid of the profile's channels."""
    padded = padded_pixels(profile)
    return Estimate(f"a hologram on a padded grid of {padded / 1e6:.3g} Mpx",
                    run_bytes(profile, colours) + HOLOGRAM_BYTES_PER_PADDED_PX * padded, {}, {})


def depth_estimate(profile: Profile, depths: int, planes: int, colours: int = 1) -> Estimate:
    """One colour's hologram of a scene with depth shown at `planes` planes, its optimiser holding the transfer
    functions of `depths` depths (a sweep's; without one, the planes)."""
    profile.require("slm", "optics", "laser")
    flat = hologram_estimate(profile, colours)
    return Estimate(f"a hologram holding {depths} depth(s) for {planes} plane(s)", flat.fixed,
                    {"depths": TRANSFER_BYTES_PER_ROI_GRID_PX * roi_grid_pixels(profile),
                     "planes": PLANE_BYTES_PER_ROI_PX * math.prod(profile.section("optics").roi)},
                    {"depths": depths, "planes": planes})


def check_depth_memory(estimate: Estimate, what: str, advice: str | None) -> None:
    """BadValueError (one line: `what`, the estimate, the limit and the most fixed planes that fit, up to MAX_PLANES,
    as `advice` formats a count) when a `depth_estimate` does not fit the memory limit. `advice` None: the caller
    offers no fixed planes (a benchmark chooses its own), so the line ends at the limit and `what` names the knob."""
    limit = memory_limit()
    if limit is None or estimate.peak <= limit:
        return
    each = estimate.per["depths"] + estimate.per["planes"]  # a fixed plane holds one depth
    fixed = min(MAX_PLANES, max(0, math.floor((limit - INTERPRETER_BYTES - estimate.fixed) / each)))
    offer = "" if advice is None else ": " + (f"{fixed} fixed plane(s) fit ({advice.format(fixed)}, no sweep)"
                                               if fixed >= 1 else "not even one plane fits")
    raise BadValueError(f"{what}: {estimate.what} needs about {size_text(estimate.peak)}, above the "
                        f"{size_text(limit)} {limit_words()}{offer} (${MAX_MEMORY_ENV} sets the limit)")


def fit_estimate(profile: Profile, patterns: int, flat: bool, fit_steps: int, colours: int = 1,
                 planes: int = 1) -> Estimate:
    """Model calibration's fit of `patterns` captured patterns (and the `flat` one) over `fit_steps` steps, on the
    largest padded grid of the profile's channels; captured at `planes` focus depths, each pattern's fields and
    gradients are propagated to every one of them (the per-pattern bytes times the planes, not measured apart)."""
    profile.require("slm", "optics", "laser")
    padded = padded_pixels(profile)
    return Estimate(f"the model fit on a padded grid of {padded / 1e6:.3g} Mpx",
                    run_bytes(profile, colours)
                    + (FIT_BYTES_PER_PADDED_PX + FIT_BYTES_PER_PATTERN_PX * planes * flat) * padded,
                    {"patterns": FIT_BYTES_PER_PATTERN_PX * planes * padded, "fit_steps": FIT_BYTES_PER_STEP},
                    {"patterns": patterns, "fit_steps": fit_steps})


# One training step (forward, propagation, ROI loss, backward, Adam; batch 1) per grid pixel: per network, the largest
# per pixel that `benchctl bench learned --grids` measured on the paper's grids (at 1088 x 1920 for all of them,
# where fixed costs weigh most; docs/reproduction.md, "What fits in 24 GiB"). A method not measured takes the
# measured network of its family and DCM factor.
TRAINING_BYTES_PER_PX = {"holonet": 4323, "holonet-dcm2": 2511, "holonet-dcm4": 921, "holonet-pyramid": 2860,
                         "ccnn": 526, "ccnn-dcm4": 490,
                         # a focal stack of 5 planes, measured at 1088 x 1920 only (docs/depth-learned.md)
                         "holonet3d": 4339, "holonet3d-dcm2": 2578, "holonet3d-dcm4": 1205}
MEASURED_AS = {("holonet", 1): "holonet", ("holonet", 2): "holonet-dcm2", ("holonet", 4): "holonet-dcm4",
               ("ccnn", 1): "ccnn", ("ccnn", 4): "ccnn-dcm4", ("holonet3d", 1): "holonet3d",
               ("holonet3d", 2): "holonet3d-dcm2", ("holonet3d", 4): "holonet3d-dcm4"}


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
                            f"{size_text(estimate.peak)}, above the {size_text(limit)} {limit_words()}: "
                            + (f"at most --batch-size {largest} fits" if largest >= 1 else
                               "use a smaller --size or a DCM variant") + f" (${MAX_MEMORY_ENV} sets the limit)")


def _count(params: Any, name: str) -> int | None:
    value = getattr(params, name, None)  # a Python procedure may use the name for another thing
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def run_estimates(profile: Profile, params: Any) -> list[Estimate]:
    """The kinds of step a procedure with parameters `params` has, as far as they tell: exposures and their
    decoding (`frames`), holograms (a hologram `method`, or CITL's `start`), model calibration's fit (`patterns`)."""
    colours = len(getattr(params, "colours", None) or profile.channels) or 1
    estimates = []
    frames = _count(params, "frames")
    if frames is not None:
        estimates += [exposure_estimate(profile, frames, _count(params, "dark_frames") or 0, colours),
                      decode_estimate(profile, colours)]
    if isinstance(getattr(params, "method", None) or getattr(params, "start", None), (str, tuple)) and \
            padded_pixels(profile):
        estimates.append(hologram_estimate(profile, colours))
    patterns = _count(params, "patterns")
    if patterns is not None:
        estimates.append(fit_estimate(profile, patterns, getattr(params, "flat", False) is True,
                                      _count(params, "fit_steps") or 0, colours,
                                      max(1, len(getattr(params, "focus_depths_mm", None) or ()))))
    return estimates


def check_memory(profile: Profile, params: Any, where: str) -> list[Estimate]:
    """The kinds of step of a procedure with parameters `params` on `profile` (`run_estimates`), checked before it
    plans (`check_estimates`)."""
    return check_estimates(run_estimates(profile, params), where)


def check_estimates(estimates: list[Estimate], where: str) -> list[Estimate]:
    """`estimates`, each checked against the memory limit: a BadValueError naming `where` and the count (or the kind
    of step) when one does not fit."""
    limit = memory_limit()
    for estimate in estimates:
        if limit is None or estimate.peak <= limit:
            continue
        words = f"at the peak of {estimate.what}, above the {size_text(limit)} {limit_words()}"
        if not estimate.per:
            raise BadValueError(f"{where}: the run needs about {size_text(estimate.peak)} {words} (${MAX_MEMORY_ENV} "
                                "sets the limit)")
        key = max(estimate.per, key=lambda k: estimate.per[k] * estimate.counts[k])
        others = ", ".join(f"{k} = {v}" for k, v in estimate.counts.items() if k != key)
        largest = estimate.largest(key, limit)
        raise BadValueError(
            f"{where}: {key} = {estimate.counts[key]} (with {others}) needs about {size_text(estimate.peak)} {words}: "
            + (f"at most {key} = {largest}" if largest >= 1 else f"not even {key} = 1 fits")
            + f" (${MAX_MEMORY_ENV} sets the limit)")
    return estimates


def peak_lines(estimates: Sequence[Estimate]) -> list[str]:
    """The dry run's line on memory: the run's peak, the kind of step it comes from, and the limit (none without
    estimates)."""
    if not estimates:
        return []
    limit = memory_limit()
    top = max(estimates, key=lambda estimate: estimate.peak)
    return [f"memory: about {size_text(top.peak)} at the run's peak, {top.what}"
            + (f"; limit {size_text(limit)} {limit_words()}" if limit is not None else "")]
