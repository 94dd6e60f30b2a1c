"""The console's focus panel: the profile's [focus] held like the other devices, moved by steps, homed, and, once the
focus is calibrated, sent to a depth by what `benchctl focus go` uses (benchctl.runner.focus_commands): the colour's
map turns the depth into steps, reached from the calibrated side, past the backlash.

An EOS lens is driven through the console's own camera (the body is opened once): each move holds the camera, so a
live-view frame is never asked for in the middle of a drive. A stage moves on its own port while the live view goes
on. Status is read after each command on the worker thread that ran it; the page's state never asks the device.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

from benchctl.capture.focus import FocusMap, parse_depth
from benchctl.console.devices import Held
from benchctl.devices.camera import Camera
from benchctl.devices.focus import Focus, open_focus
from benchctl.errors import BadValueError, BenchctlError
from benchctl.profiles import Profile
from benchctl.runner.focus_commands import calibrated_colour, go_to

MAX_STEPS = 10_000_000  # one move from the page: far beyond any mechanism's travel, short of a typo's


class FocusControl:
    """The profile's focus held by the console; `maps` gives the focus calibration in effect (per colour)."""

    def __init__(self, profile: Profile, camera: Held[Camera] | None, maps: Callable[[], dict[str, FocusMap]],
                 say: Callable[[str], None]) -> None:
        self.profile = profile
        self.config = profile.section("focus")
        self.camera = camera if self.config.driver == "eos" else None  # the lens is driven through it
        self.held: Held[Focus] = Held("focus", self._open, Focus.close)
        self.maps = maps
        self.say = say
        self.moving: str | None = None  # the command under way
        self.last: str | None = None  # what the last command did, in words
        self.status: dict[str, Any] = {}  # as last read: position, the device's counter, unit, side approached from
        self.unread: str | None = None  # why the last read failed

    def _open(self) -> Focus:
        if self.camera is None:
            return open_focus(self.profile)
        with self.camera.use() as camera:
            return open_focus(self.profile, camera)

    def connect(self) -> bool:
        connected = self.held.connect()
        self.refresh()
        return connected

    @contextlib.contextmanager
    def _use(self, what: str) -> Iterator[Focus]:
        """The focus for one command (with the camera first when the lens is the camera's); its status read after."""
        with self.camera.use() if self.camera is not None else contextlib.nullcontext(), self.held.use() as focus:
            self.moving = what
            try:
                yield focus
            finally:
                self.moving = None
                self._read(focus)

    # -- commands ----------------------------------------------------------------------------------------------

    def move(self, steps: int) -> dict[str, Any]:
        """Move `steps` (signed) from where the focus is."""
        if isinstance(steps, bool) or not isinstance(steps, int) or abs(steps) > MAX_STEPS:
            raise BadValueError(f"focus steps must be a whole number of at most {MAX_STEPS:,} either way, "
                                f"got {steps!r}")
        with self._use(f"move {steps:+d}") as focus:
            line = focus.move(steps).describe(focus.unit)
        return self._done(line)

    def home(self) -> dict[str, Any]:
        """Drive to the home end stop: position 0 from then on."""
        with self._use("home") as focus:
            line = focus.home().describe(focus.unit)
        return self._done(line)

    def go(self, depth: str, channel: str | None) -> dict[str, Any]:
        """Focus at `depth` ('70.5mm', '14.2D') for `channel` as `benchctl focus go` does: through the colour's focus
        calibration, from the calibrated side past the backlash; homes first where the position is unknown."""
        target_m = parse_depth(str(depth))
        channel, found = calibrated_colour(self.profile, self.maps(), channel)
        with self._use(f"go {target_m * 1e3:.4g} mm") as focus:
            steps, move = go_to(focus, found, target_m)
            line = (f"{channel} at {target_m * 1e3:.4g} mm from the SLM is {steps} {focus.unit}(s): "
                    f"{move.describe(focus.unit)}")
        return self._done(line)

    def _done(self, line: str) -> dict[str, Any]:
        """What a command did, said, kept for the page and answered with the status read after it."""
        self.last = line
        self.say(f"focus: {line}")
        return {"moved": line, **self.status, **self.where()}

    # -- state ------------------------------------------------------------------------------------------------

    def refresh(self) -> None:
        """Read the focus's status now (on a worker thread; the device may be asked)."""
        if not self.held.connected:
            self.status = {}
            return
        try:
            with self.held.use() as focus:
                self._read(focus)
        except BenchctlError as exc:
            self.status, self.unread = {}, str(exc)

    def _read(self, focus: Focus) -> None:
        try:
            status = focus.status()
        except BenchctlError as exc:
            self.status, self.unread = {}, str(exc)
            return
        self.status, self.unread = status, None

    def where(self) -> dict[str, Any]:
        """Where the focus was last read to be (no device asked): the command under way, the position, its unit and,
        through the focus calibration now in effect, the depth it focuses at per calibrated colour."""
        position = self.status.get("position")
        return {"moving": self.moving, "position": position, "unit": self.status.get("unit"),
                "depth_mm": {} if position is None else {
                    colour: round(found.depth_mm(position), 4) for colour, found in self.maps().items()}}

    def state(self) -> dict[str, Any]:
        """What the page shows (no device asked): connection, `where`, the device's own counter, the calibrated depth
        range per colour and the last command's result."""
        return {"connected": self.held.connected, "error": self.unread or self.held.error, "last": self.last,
                **self.status, **self.where(),
                "calibrated": {colour: _depth_range(found) for colour, found in self.maps().items()}}


def _depth_range(found: FocusMap) -> list[float]:
    """The depths (mm) a colour's calibration covers, nearest first."""
    ends = [found.depth_mm(steps) for steps in found.range_steps]
    return [round(min(ends), 4), round(max(ends), 4)]
