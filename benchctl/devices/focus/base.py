"""The camera's focus: the `Focus` interface. Public methods here; drivers implement the hooks.

Open-loop steps are not positions. A move records what was asked (`requested`) and where benchctl believes the focus
is afterwards (`position`, in steps from the home end stop, None until homed), beside what the device itself reports
where it reports anything. Mechanics lose motion when the direction reverses (backlash), so `move_to` arrives at a
position always moving the same way, first stepping past it by `overshoot` steps when it has to come back: the focus
calibration measures the backlash and says which way and how far.
"""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

from benchctl.devices.connection import Connection
from benchctl.devices.errors import DeviceError
from benchctl.devices.safety import wait
from benchctl.errors import BadValueError
from benchctl.profiles import FocusConfig, Profile


@dataclass(frozen=True)
class FocusMove:
    """One move: the steps asked for, the believed position after it (steps from home; None: not homed) and the
    device's own position counter where it has one (a stage's; a lens driven over PTP reports none)."""

    requested: int
    position: int | None
    reported: int | None = None

    def describe(self, unit: str) -> str:
        where = "unknown (not homed since connecting)" if self.position is None else f"{self.position} {unit}(s)"
        told = "" if self.reported is None else f"; the device reports {self.reported}"
        return f"moved {self.requested:+d} {unit}(s); believed position {where}{told}"


class Focus(Connection):
    """A focus mechanism built from the profile's [focus] section; a context manager (open on enter, close on exit)."""

    driver: ClassVar[str]
    unit: ClassVar[str] = "step"  # what one step is, for people
    counts_steps: ClassVar[bool] = False  # the device's own counter is the position once homed (a stage's is)

    def __init__(self, config: FocusConfig) -> None:
        self.config = config
        self._position: int | None = None
        self._direction = 0  # the sign of the last motion: the side the focus was last approached from

    @classmethod
    def for_profile(cls, profile: Profile) -> Focus:
        """This driver for `profile`'s [focus] section, not yet connected; drivers that need more of the profile
        override it."""
        return cls(profile.section("focus"))

    # -- hooks --------------------------------------------------------------------------------------------------

    @abstractmethod
    def _identity(self) -> dict[str, str]:
        """What the device says it is."""

    @abstractmethod
    def _drive(self, steps: int) -> int | None:
        """Move `steps` (signed) relative to here and wait until the motion ends; the device's own position counter
        afterwards, or None where it has none."""

    @abstractmethod
    def _home(self) -> None:
        """Move to the home end stop (position 0) and wait until the motion ends."""

    def _reported(self) -> int | None:
        """The device's own position counter now, where it has one."""
        return None

    def ground_truth(self) -> dict[str, float] | None:
        """Where the mechanism truly is and its hidden backlash, in this driver's steps, as far as the device knows: a
        simulated mechanism knows what calibration should find; a real one does not (None)."""
        return None

    # -- public -------------------------------------------------------------------------------------------------

    @property
    def position(self) -> int | None:
        """Where benchctl believes the focus is, in steps from home (None: not homed since connecting)."""
        return self._position

    @property
    def travel(self) -> int | None:
        """The last position from home the mechanism reaches, where the device says (None: not known)."""
        return None

    @property
    def direction(self) -> int:
        """+1 or -1: the direction of the last motion (0: none yet)."""
        return self._direction

    def identity(self) -> dict[str, str]:
        """What the device says it is, plus the driver name."""
        self._require_open()
        return {"driver": self.driver, **self._identity()}

    def status(self) -> dict[str, Any]:
        """Believed position, the device's own counter, the side it was last approached from."""
        self._require_open()
        return {"position": self._position, "reported": self._reported(), "unit": self.unit,
                "approached_from": {1: "below", -1: "above", 0: "not moved yet"}[self._direction]}

    def home(self) -> FocusMove:
        """Move to the home end stop; the believed position is 0 from then on (approached from above)."""
        self._require_open()
        self._home()
        self._position, self._direction = 0, -1
        self._settle()
        return FocusMove(0, 0, self._reported())

    def move(self, steps: int) -> FocusMove:
        """Move `steps` (signed) from here; the believed position follows what was asked."""
        self._require_open()
        if isinstance(steps, bool) or not isinstance(steps, int):
            raise BadValueError(f"focus steps must be a whole number, got {steps!r}")
        reported = self._drive(steps) if steps else self._reported()
        if steps:
            self._direction = 1 if steps > 0 else -1
        if self.counts_steps and self._position is not None and reported is not None:
            self._position = reported
        elif self._position is not None:
            self._position += steps
        self._settle()
        return FocusMove(steps, self._position, reported)

    def move_to(self, position: int, approach: int = 1, overshoot: int = 0) -> FocusMove:
        """Move to `position` (steps from home), arriving while moving in direction `approach` (+1 or -1): where
        the focus would otherwise arrive the other way, it first goes `overshoot` steps past the position. Homes
        first if the position is not known."""
        if approach not in (1, -1):
            raise BadValueError(f"approach must be +1 or -1, got {approach!r}")
        if overshoot < 0:
            raise BadValueError(f"overshoot must be >= 0 steps, got {overshoot}")
        if self.position is None:
            self.home()
        assert self._position is not None
        requested = position - self._position
        if requested * approach < 0 or (requested == 0 and self._direction != approach):
            past = position - approach * overshoot  # never beyond the home end stop or the travel's end
            past = max(past, 0) if self.travel is None else min(max(past, 0), self.travel)
            self.move(past - self._position)
        assert self._position is not None
        last = self.move(position - self._position)
        return FocusMove(requested, last.position, last.reported)

    def _settle(self) -> None:
        wait(self.config.settle_ms * 1e-3)

    def _require_open(self) -> None:
        if not self._open_now:
            raise DeviceError(f"{self.driver} focus is not open")
