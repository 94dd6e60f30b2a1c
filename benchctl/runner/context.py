"""What a procedure is made of: its Parameters, its Steps with the exposures they declare, and the Context every
step runs in.

A step declares each exposure it makes (`Expose`: which channel, at what power, how many frames), so the plan can
be checked against the profile's limits and printed before anything runs, and a step that tries an exposure it
did not declare is stopped before the laser is touched. Likewise each focus move (`FocusAt`: the depth, the position
the focus calibration gives it and the side it is approached from), which the dry run lists with its time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch

from benchctl.calibration.acceptance import Verdict, rejection_line
from benchctl.calibration.calibrated import Calibrated
from benchctl.calibration.store import Calibration
from benchctl.devices.power import format_power
from benchctl.devices.slm import SLM
from benchctl.errors import BenchctlError
from benchctl.files import file_sha256
from benchctl.memory import Estimate
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile
from benchctl.runner import layout
from benchctl.runner.instruments import Exposure, Instruments
from benchctl.runner.record import RunRecord, file_problem, set_aside
from benchctl.schema import Model
from benchctl.terminal import ProgressLine

POWER_TOLERANCE = 1e-9  # relative: a power equal to its limit in the last bits is at the limit


class Parameters(Model, kw_only=True):
    """Base of every procedure's parameters (its PARAMETERS model; the file's [parameters] table is decoded into
    it). Groups that several procedures share derive from it (`ExposureParameters`, `HologramParameters`)."""

    def applied_to(self, profile: Profile) -> Profile:
        """The profile the run uses: parameters that override a profile setting say so here (none by default)."""
        return profile


P = TypeVar("P", bound=Parameters)


@dataclass(frozen=True)
class Expose:
    """An exposure a step declares: show a frame, light `channel` alone at `power_w` (None: a power the step
    decides when it runs, never above `max_w`, else the channel's max_power_mw), capture `frames` RAW frames and then
    `dark_frames` with emission off; `keep`: the RAW files are kept in the run folder (its disk estimate counts
    them); `times`: how many such exposures the step makes (its time estimate counts each)."""

    channel: str
    power_w: float | None
    frames: int
    dark_frames: int
    keep: bool = True
    times: int = 1  # how many such exposures the step makes (a sweep makes one per position)
    max_w: float | None = None

    def describe(self) -> str:
        power = (format_power(self.power_w) if self.power_w is not None else "a power chosen when the step runs"
                 + (f" (at most {format_power(self.max_w)})" if self.max_w is not None else ""))
        return (f"{f'{self.times} x ' if self.times > 1 else ''}{self.channel} alone at {power}, {self.frames} "
                f"frame(s) + {self.dark_frames} dark" + ("" if self.keep else ", RAW not kept"))


@dataclass(frozen=True)
class FocusAt:
    """A focus move a step declares: focus at `depth_m` from the SLM for `channel`, which its focus calibration puts
    at `steps` from home, arriving while moving in direction `approach` after going `overshoot` steps past where it
    has to come back (`Focus.move_to`)."""

    channel: str
    depth_m: float
    steps: int
    approach: int
    overshoot: int

    def describe(self) -> str:
        side = "below" if self.approach > 0 else "above"
        return f"focus {self.channel} at {self.depth_m * 1e3:.2f} mm: {self.steps} steps from home, from {side}"


@dataclass(frozen=True)
class Step:
    """One resumable piece of a run: `action(context)` does it and returns a JSON-ready result; `exposes` declares
    every exposure it makes (a step without any uses no device), `focus` every focus move."""

    key: str
    description: str
    action: Callable[[Context], dict[str, Any]]
    exposes: tuple[Expose, ...] = ()
    focus: tuple[FocusAt, ...] = ()
    memory: Estimate | None = None  # its peak, where the procedure's parameters alone do not tell it (`run_estimates`)

    @property
    def devices(self) -> tuple[str, ...]:
        """The devices the step uses: all three when it exposes, none otherwise; the focus when it moves it."""
        return ("laser", "slm", "camera") * bool(self.exposes) + ("focus",) * bool(self.focus)


class StepRedo(BenchctlError):
    """A step found that an earlier step's work must be done again: a file it reads is damaged or missing, or the
    state it continues from diverged. `redo` names that step (done again with every step that finished after it);
    the run does it now, or with `stop` the run stops and a resume does it. `diverged`: the redone step may lower its
    learning rate (`Context.divergences` counts how often this happened to it)."""

    def __init__(self, message: str, redo: str, *, stop: bool = False, diverged: bool = False) -> None:
        super().__init__(message)
        self.redo, self.stop, self.diverged = redo, stop, diverged


def check_exposures(steps: list[Step], profile: Profile) -> None:
    """Every declared exposure names a laser channel of `profile`, at a power within its max_power_mw, with at
    least one frame: checked when planning, before anything is touched (BenchctlError naming the step)."""
    for step in steps:
        for expose in step.exposes:
            channel = profile.channel(expose.channel)
            if expose.power_w is not None and not 0 <= expose.power_w <= _limit_w(channel.max_power_mw):
                raise BenchctlError(f"step {step.key!r}: {expose.channel} at {format_power(expose.power_w)} is "
                                    f"outside 0..max_power_mw {channel.max_power_mw:g} mW")
            if expose.frames < 1 or expose.dark_frames < 0:
                raise BenchctlError(f"step {step.key!r}: {expose.frames} frame(s) + {expose.dark_frames} dark: "
                                    "an exposure captures at least one frame")


def _limit_w(max_power_mw: float) -> float:
    return max_power_mw * 1e-3 * (1 + POWER_TOLERANCE)


@dataclass
class Context:
    """What a step sees: the bench as calibrated for this run (the profile with this run's calibration and
    parameters applied, its optical setups and SLM encoder), the parameters, the instruments, the run record, and
    the step running now."""

    bench: Calibrated
    params: Parameters
    instruments: Instruments
    record: RunRecord | None = None  # None during a dry run
    say: Callable[[str], None] = print
    step: Step | None = None  # set by the engine while a step runs
    # files the running step wrote: run-relative path -> SHA-256, for later steps to read / as a record only
    written: dict[str, dict[str, str]] = field(default_factory=lambda: {"checksums": {}, "archived": {}}, repr=False)

    @property
    def profile(self) -> Profile:
        """The profile in effect: the bench's, with this run's calibration and parameters applied."""
        return self.bench.profile

    @property
    def calibration(self) -> Calibration:
        """The calibration this run uses (the store during a dry run, the run's own copy once it runs)."""
        assert self.bench.calibration is not None
        return self.bench.calibration

    def recalibrated(self) -> None:
        """Apply what a step of this run measured (lookup tables, optical model) to the bench later steps use."""
        self.bench = self.bench.recalibrated()

    def save_calibration(self, save: Callable[[Calibration], object]) -> None:
        """Store what a step measured, with `save`, in this run's calibration and in the profile's store (where later
        runs find it), and use it from now on."""
        for calibration in (self.calibration, Calibration.store(self.calibration.profile)):
            save(calibration)
        if self.record is not None:
            self.record.calibration_written(self.calibration.checksums(), self.step.key if self.step else None)
        self.recalibrated()

    def store_calibration(self, verdict: Verdict, save: Callable[[Calibration], object],
                          candidate: dict[str, Callable[[Path], object]]) -> dict[str, Any]:
        """Store a new calibration with `save` (`save_calibration`) if `verdict` passed its acceptance test, or if the
        procedure's `accept` is "always" and there is something to store; else keep it for inspection, each file of
        `candidate` (name -> writer of that file) written beside the store and into this run's calibration copy
        (`Calibration.rejected_path`), and the old one stays. Says which, in one line; returns the record a step keeps
        (`Verdict.record`), which ends the run with an error once its steps are done when not stored."""
        forced = getattr(self.params, "accept", "tested") == "always" and bool(candidate)
        what = f"      {verdict.colour}: {verdict.kind}"
        if verdict.passed or forced:
            self.save_calibration(save)
            if verdict.passed:
                self.say(f"{what} stored: {verdict.residuals()}")
            else:
                self.say(f"{what} stored although it failed its acceptance test (accept = \"always\"): "
                         f"{'; '.join(verdict.failures)}; {verdict.residuals()}")
            return verdict.record(True, [])
        run = self.record.name if self.record is not None else "dry-run"
        kept = []
        for calibration in (Calibration.store(self.calibration.profile), self.calibration):
            for name, write in candidate.items():
                path = calibration.rejected_path(run, name)
                write(path)
                kept.append(str(path))
        record = verdict.record(False, kept)
        self.say(f"      {rejection_line(record)}; {verdict.residuals()}")
        return record

    def parameters(self, kind: type[P]) -> P:
        """The procedure's parameters as `kind`: its PARAMETERS or a group they derive from, which the shared
        steps need (ExposureParameters for exposure steps)."""
        if not isinstance(self.params, kind):
            raise BenchctlError(f"the procedure's PARAMETERS ({type(self.params).__name__}) must derive from "
                                f"{kind.__module__}.{kind.__name__} for this step")
        return self.params

    def setup(self, channel: str, *, as_displayed: bool = False) -> OpticalSetup:
        """`channel`'s optical setup for this run (`Calibrated.setup`)."""
        return self.bench.setup(channel, as_displayed=as_displayed)

    @property
    def slm(self) -> SLM:
        """The profile's SLM as an encoder (phase <-> gray levels as displayed): the panel itself is not opened."""
        return self.bench.slm

    def encode(self, phase: np.ndarray | torch.Tensor, channel: str) -> np.ndarray:
        """The SLM frame (gray levels) that shows `phase` for `channel`."""
        return self.bench.encode(phase, channel)

    def decode(self, gray: np.ndarray, channel: str) -> np.ndarray:
        """The phase an SLM frame shows for `channel` (the inverse of `encode`, to its gray-level step)."""
        return self.bench.decode(gray, channel)

    def divergences(self, key: str) -> int:
        """How often a later step found that step `key`'s work diverged and sent the run back to it (StepRedo with
        `diverged`): the step halves its learning rate that many times."""
        return self.record.divergences.get(key, 0) if self.record is not None else 0

    def result(self, key: str) -> dict[str, Any]:
        """The result a finished step recorded (this run, or the run being resumed)."""
        if self.record is None:
            raise BenchctlError(f"step {key!r}: no results during a dry run")
        return self.record.result(key)

    def path(self, relative: str) -> Path:
        """The run folder's file `relative` (as `runner.layout` names it and step results record it); parent
        folders are created."""
        if self.record is None:
            raise BenchctlError("no run folder during a dry run")
        return self.record.path(*Path(relative).parts)

    def wrote(self, relative: str, *, read_later: bool = True) -> str:
        """Note that the running step wrote the run folder's file `relative`: its SHA-256 joins the step's result
        ("checksums" for a file later steps read, verified before they use it and when the run is resumed; "archived"
        for a record no step reads). Returns `relative`."""
        if self.step is not None:
            self.written["checksums" if read_later else "archived"][relative] = file_sha256(self.path(relative))
        return relative

    def verified(self, relative: str) -> Path:
        """The run folder's file `relative`, checked against the SHA-256 the step that wrote it recorded: a missing
        or changed one sends the run back to that step (StepRedo), which writes it again."""
        path = self.path(relative)
        writer = self.record.writer_of(relative) if self.record is not None else None
        if writer is not None:
            problem = file_problem(path, writer[1])
            if problem:
                raise StepRedo(f"{relative}{problem}", writer[0])
        return path

    def progress(self, label: str) -> ProgressLine:
        return ProgressLine(label)

    def focus_at(self, at: FocusAt) -> dict[str, Any]:
        """Move the focus as the running step declared (`FocusAt`); returns the JSON-ready record of the move: the
        depth, the position asked for, what was requested, the believed position and the device's own counter. A move
        the step did not declare is refused before the focus is touched."""
        step = self.step
        if step is None:
            raise BenchctlError("a focus move outside a running step")
        if at not in step.focus:
            raise BenchctlError(f"step {step.key!r} moves the focus ({at.describe()}), which it did not declare "
                                "(declared: " + ("; ".join(f.describe() for f in step.focus) or "no focus move") + ")")
        move = self.instruments.focus.move_to(at.steps, at.approach, at.overshoot)
        return {"depth_mm": round(at.depth_m * 1e3, 6), "steps": at.steps, "requested": move.requested,
                "position": move.position, "reported": move.reported}

    def expose(self, channel: str, power_w: float, frame: np.ndarray, *, frames: int, dark_frames: int,
               keep: bool = True, within: str | None = None) -> Exposure:
        """One exposure the running step declared (see `Instruments.expose`); with `keep`, its RAW frames are
        saved in the step's raw folder, or its sub-folder `within` for a step that keeps several exposures (what an
        unfinished earlier attempt left there is set aside first), else they stay in memory. An exposure the step
        did not declare is refused before any device is touched."""
        step = self.step
        if step is None:
            raise BenchctlError("an exposure outside a running step")
        max_mw = self.profile.channel(channel).max_power_mw
        if power_w > _limit_w(max_mw):
            raise BenchctlError(f"step {step.key!r} exposes {channel} at {format_power(power_w)}, above the channel's "
                                f"max_power_mw {max_mw:g} mW")
        if not any(_allows(expose, channel, power_w, frames, dark_frames) for expose in step.exposes):
            raise BenchctlError(f"step {step.key!r} exposes {channel} at {format_power(power_w)}, {frames} frame(s) "
                                f"+ {dark_frames} dark, which it did not declare (declared: "
                                + ("; ".join(e.describe() for e in step.exposes) or "no exposure") + ")")
        folder = None
        if keep:
            folder = self.path(layout.raw_folder(step.key, within))
            set_aside(folder)
        return self.instruments.expose(folder, channel, power_w, frame, frames=frames, dark_frames=dark_frames)


def _allows(expose: Expose, channel: str, power_w: float, frames: int, dark_frames: int) -> bool:
    """Whether `expose` declared this exposure (a power chosen at run time: within its max_w, else the channel's
    limit, which `Context.expose` checks too)."""
    bound = expose.power_w if expose.power_w is not None else expose.max_w
    limit = bound * (1 + POWER_TOLERANCE) if bound is not None else float("inf")
    return (expose.channel == channel and 0 <= power_w <= limit and expose.frames == frames
            and expose.dark_frames == dark_frames)
