"""The simulated focus mechanism: where the camera of the simulated bench truly focuses, and the mechanics between a
driver's steps and that plane, which focus calibration has to recover ([sim.focus], docs/focus.md).

One mechanism per simulated bench, its state kept in the simulated bench's state folder (`sim-focus`), moved by
whichever simulated device drives it (the Zaber stage on a sim:// port, the simulated EOS body's DriveLens):

- each nominal step moves the carriage (or lens group) 1 + spread x N(0, 1) steps (drawn per move from the
  stream (seed, move number), so a run after `benchctl sim reset` repeats);
- backlash: on a reversal the first `backlash_steps` of motion only take up the play;
- end stops at 0 and `range_steps`: driving into one moves nothing further (the drive slips, as a lens's does);
- the camera focuses at depth plane_mm + mm_per_step x (true position - start_steps) from the SLM (plane_mm: the
  optics' distance unless given, so an untouched mechanism focuses on the target plane).
"""

from __future__ import annotations

import math
from typing import Any

import msgspec
import numpy as np

from benchctl.devices.sim.state import load_state, save_state
from benchctl.profiles import SimFocusConfig

FOCUS_STATE = "sim-focus"


def bind(config: SimFocusConfig) -> None:
    """Make `config` (a profile's [sim.focus]) the mechanism's hidden values for the devices that drive it: a
    simulated device opened through a sim:// URL sees no profile, so the driver's `for_profile` leaves them here."""
    state = load_state(FOCUS_STATE)
    save_state(FOCUS_STATE, {**state, "kind": "focus", "config": msgspec.to_builtins(config)})


def bound_config() -> SimFocusConfig:
    """The hidden values `bind` left, else the defaults."""
    saved = load_state(FOCUS_STATE).get("config")
    return msgspec.convert(saved, SimFocusConfig) if saved else SimFocusConfig()


class Mechanism:
    """The hidden focus mechanics (see the module docstring), loaded from and saved to the simulated bench's state."""

    def __init__(self, config: SimFocusConfig | None = None, distance_mm: float | None = None) -> None:
        self.config = config or bound_config()
        self.distance_mm = distance_mm
        state = load_state(FOCUS_STATE)
        self.true_steps = float(state.get("true_steps", self.config.start_steps))
        # Play taken up on the positive side: backlash_steps after a positive move, 0 after a negative one.
        self.play = float(state.get("play", 0.0))
        self.moves = int(state.get("moves", 0))

    @property
    def plane_m(self) -> float | None:
        """Depth of the camera's focus plane from the SLM, metres (None: neither plane_mm nor the optics' distance
        is known)."""
        config = self.config
        at_start = config.plane_mm if config.plane_mm is not None else self.distance_mm
        if at_start is None:
            return None
        return (at_start + config.mm_per_step * (self.true_steps - config.start_steps)) * 1e-3

    def drive(self, steps: float) -> float:
        """Drive `steps` nominal steps (signed); returns the true motion of the carriage (saved at once)."""
        if steps == 0:
            return 0.0
        config = self.config
        self.moves += 1
        motion = float(steps)
        if config.step_spread:
            rng = np.random.default_rng([config.seed, self.moves])
            # the sum of |steps| independent step sizes: its spread grows as the square root of their number
            motion += config.step_spread * math.sqrt(abs(steps)) * float(rng.standard_normal())
        backlash = config.backlash_steps
        if motion > 0:
            taken = min(motion, backlash - self.play)
            self.play += taken
        else:
            taken = max(motion, -self.play)
            self.play += taken
        before = self.true_steps
        self.true_steps = min(max(before + motion - taken, 0.0), float(config.range_steps))
        self.save()
        return self.true_steps - before

    def at_end_stop(self) -> bool:
        return self.true_steps <= 0.0 or self.true_steps >= self.config.range_steps

    def save(self) -> None:
        save_state(FOCUS_STATE, {**load_state(FOCUS_STATE), "kind": "focus", "true_steps": self.true_steps,
                                 "play": self.play, "moves": self.moves})

    def hidden(self) -> dict[str, Any]:
        """The values a calibration should recover, for comparisons in tests and figures."""
        config = self.config
        return {"true_steps": self.true_steps, "backlash_steps": config.backlash_steps,
                "step_spread": config.step_spread, "mm_per_step": config.mm_per_step, "plane_m": self.plane_m}
