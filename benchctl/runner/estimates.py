"""How long a run will take and how much disk it fills, estimated from its plan before it starts: the dry run prints
both, a run refuses to start where the disk lacks the space, and each step's line says how long the rest will take.

Time: every exposure a step declares costs its frames' capture time, plus the SLM's settle time; every focus move
FOCUS_MOVE_SECONDS plus the focus's settle time; a step that does neither (a hologram, a fit, processing)
STEP_SECONDS. Once steps of a kind have run, their measured mean replaces
the estimate for the rest of that kind. Disk: each RAW frame a step keeps, and DISK_MARGIN more for holograms, images
and records. A frame's size and capture time are the camera driver's (`frame_size`: a GenICam camera's region and
pixel format, the simulated camera's rendering of [sim.sensor], a body's sensor).
"""

from __future__ import annotations

import shutil
import statistics
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

from benchctl.devices.camera import frame_size
from benchctl.errors import BenchctlError
from benchctl.memory import size_text
from benchctl.profiles import Profile
from benchctl.runner.context import Step

STEP_SECONDS = 1.0  # a step that exposes nothing, until one of its kind has run
FOCUS_MOVE_SECONDS = 0.5  # one focus move's travel (a stage's few mm, a lens's few drives), until measured
DISK_MARGIN = 1.1


def frame_bytes(profile: Profile) -> float:
    """Bytes of one RAW frame of the profile's camera, as its driver expects it."""
    return frame_size(profile).file_bytes


def _kind(step: Step) -> tuple[str, bool]:
    return step.key.split("/")[0], bool(step.exposes or step.focus)


def duration_text(seconds: float) -> str:
    """'45 s', '3 min 40 s', '2 h 05 min'."""
    seconds = max(0, round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


class RunEstimate:
    """A plan's time and disk, and how much time is left once some steps have run."""

    def __init__(self, steps: Sequence[Step], profile: Profile) -> None:
        self.profile = profile
        self.frame = frame_size(profile)
        self.frame_s = self.frame.seconds
        settle = (profile.slm.settle_ms if profile.slm else 0.0) / 1e3
        self.move_s = FOCUS_MOVE_SECONDS + (profile.focus.settle_ms / 1e3 if profile.focus else 0.0)
        self.planned = {step.key: sum(((e.frames + e.dark_frames) * self.frame_s + settle) * e.times
                                      for e in step.exposes) + len(step.focus) * self.move_s
                        if step.exposes or step.focus else STEP_SECONDS for step in steps}
        self.measured: dict[tuple[str, bool], list[float]] = {}
        self._count: Counter[tuple[str, bool]] = Counter()  # steps left, per kind
        self._planned: dict[tuple[str, bool], float] = {}  # their planned seconds, per kind

    def start(self, todo: Sequence[Step]) -> None:
        """The steps still to run, in order (again after a step sent the run back: StepRedo)."""
        self._count = Counter(_kind(step) for step in todo)
        self._planned = {}
        for step in todo:
            self._planned[_kind(step)] = self._planned.get(_kind(step), 0.0) + self.planned[step.key]

    def ran(self, step: Step, seconds: float) -> None:
        """A step finished in `seconds`: the rest of its kind are estimated from what those took."""
        kind = _kind(step)
        self.measured.setdefault(kind, []).append(seconds)
        self._count[kind] -= 1
        self._planned[kind] -= self.planned[step.key]

    def left(self) -> float:
        """The time the steps still to run (`start`, less those that `ran`) should take."""
        return sum(statistics.fmean(self.measured[kind]) * count if kind in self.measured else self._planned[kind]
                   for kind, count in self._count.items() if count > 0)

    def seconds(self, steps: Sequence[Step]) -> float:
        """The time `steps` should take."""
        total = 0.0
        for step in steps:
            seen = self.measured.get(_kind(step))
            total += statistics.fmean(seen) if seen else self.planned[step.key]
        return total

    def frames(self, steps: Sequence[Step]) -> tuple[int, int]:
        """(frames exposed, RAW frames kept on disk) by `steps`."""
        exposed = sum((e.frames + e.dark_frames) * e.times for step in steps for e in step.exposes)
        kept = sum((e.frames + e.dark_frames) * e.times for step in steps for e in step.exposes if e.keep)
        return exposed, kept

    def disk_bytes(self, steps: Sequence[Step]) -> float:
        return self.frames(steps)[1] * frame_bytes(self.profile) * DISK_MARGIN

    def describe(self, steps: Sequence[Step], out: Path) -> list[str]:
        """The dry run's lines: time and disk, with what they rest on."""
        exposed, kept = self.frames(steps)
        computing = sum(1 for step in steps if not step.exposes and not step.focus)
        moves = sum(len(step.focus) for step in steps)
        focus = f", {moves} focus move(s) at about {self.move_s:.1f} s each" if moves else ""
        return [f"time: about {duration_text(self.seconds(steps))} ({exposed} frame(s) at about {self.frame_s:.1f} s "
                f"each with {self.frame.what}{focus}, {computing} other step(s) at about {STEP_SECONDS:g} s until "
                "measured)",
                f"disk: about {size_text(self.disk_bytes(steps))} in {out} ({kept} RAW frame(s) of "
                f"{size_text(frame_bytes(self.profile))} kept, {DISK_MARGIN - 1:.0%} more for holograms and images); "
                f"{size_text(free_bytes(out))} free there"]

    def check_disk(self, steps: Sequence[Step], out: Path) -> None:
        """BenchctlError (one line) when the disk holding `out` lacks the space `steps` will fill."""
        needed, free = self.disk_bytes(steps), free_bytes(out)
        if needed > free:
            raise BenchctlError(f"{out}: {size_text(free)} free, and this run keeps about {size_text(needed)} of RAW "
                                f"frames ({self.frames(steps)[1]} of {size_text(frame_bytes(self.profile))}): free "
                                "some space (benchctl runs remove ...) or write the run elsewhere (--out DIR)")


def free_bytes(folder: Path) -> int:
    """Free bytes on the disk that holds `folder` (or its nearest existing parent)."""
    path = Path(folder).resolve()
    while not path.exists():
        path = path.parent
    return shutil.disk_usage(path).free
