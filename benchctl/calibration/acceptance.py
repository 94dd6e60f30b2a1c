"""Acceptance of a new calibration: a fitted optical model, a lookup table or a camera-SLM registration replaces the
stored one only when it passes its test: there was signal (light reached the camera), the fit improved on its start,
its residual is below a stated bound and not above the residual of what it replaces, measured on the same captures;
those captures are ones the new calibration was not fitted to wherever it has a fit to judge (a model's held-out
patterns, a table's held-out gray levels), since on its own captures a fit is right by construction.

A calibration that fails is not stored: the old one stays, the new one is kept for inspection beside the store and
in the run's own calibration copy (`rejected/<run>-<file>`), the run says so in one line and in its report, and it
ends with an error (rc != 0) once its steps are done. The procedure's `accept = "always"` stores it anyway (said, and
in the report).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

NO_WORSE_TOLERANCE = 0.02
"""A new calibration may leave its residual at most this fraction above the stored one's on the same captures."""
AcceptMode = Literal["tested", "always"]
""""tested": a new calibration replaces the stored one only if it passes its acceptance test; "always": it is stored
even when it fails (said, and in the report)."""


def _number(value: float | None) -> str:
    return "none" if value is None else f"{value:.4g}"


@dataclass
class Verdict:
    """A new calibration's acceptance test: what it is, its residual (`measure` says which) and that of what it would
    replace on the same captures (`replaces` names that: "stored one", or the default in use without one, such as
    "linear table" or "ideal model"; `old` None: nothing to compare with), and the checks it failed (none:
    accepted)."""

    kind: str  # "optical model", "lookup table", "registration"
    colour: str
    measure: str  # what `new` and `old` are, e.g. "held-out residual"
    new: float | None
    old: float | None
    failures: list[str] = field(default_factory=list)
    details: dict[str, Any] = field(default_factory=dict)  # further numbers for the report (JSON-ready)
    replaces: str = "stored one"

    def check(self, passed: bool, failure: str) -> None:
        """Note `failure` (a short clause with its numbers) unless `passed`."""
        if not passed:
            self.failures.append(failure)

    def no_worse(self) -> None:
        """The check every kind makes: the new residual is not above that of what it replaces on the same captures
        (by more than NO_WORSE_TOLERANCE: a recalibration of an unchanged bench lands within its noise)."""
        if self.new is not None and self.old is not None:
            self.check(self.new <= self.old * (1 + NO_WORSE_TOLERANCE),
                       f"{self.measure} {self.new:.4g} is above the {self.replaces}'s {self.old:.4g} on the same "
                       "captures")

    @property
    def passed(self) -> bool:
        return not self.failures

    def residuals(self) -> str:
        """The comparison, worded so that it holds whatever was stored: 'held-out residual 0.03 (new) against 0.2
        (stored one), on the same captures', or '... 0.03 (new); nothing to compare with'."""
        if self.old is None:
            return f"{self.measure} {_number(self.new)} (new); nothing to compare with"
        return (f"{self.measure} {_number(self.new)} (new) against {_number(self.old)} ({self.replaces}), on the same "
                "captures")

    def record(self, stored: bool, kept: list[str]) -> dict[str, Any]:
        """The JSON-ready record a step keeps (`stored`: it replaced the old one; `kept`: where a rejected one is)."""
        return {"kind": self.kind, "colour": self.colour, "measure": self.measure, "new": self.new, "old": self.old,
                "replaces": self.replaces, "failures": list(self.failures), "stored": stored,
                "forced": stored and not self.passed, "kept": kept, **self.details}


def rejection_line(record: dict[str, Any]) -> str:
    """One line for a calibration a step did not store (a `Verdict.record`)."""
    kept = f"; the new one is kept as {record['kept'][0]}" if record.get("kept") else ""
    return (f"{record['colour']}: new {record['kind']} not stored ({'; '.join(record['failures'])}); the "
            f"{record.get('replaces', 'stored one')} stays{kept}")
