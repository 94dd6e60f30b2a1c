"""The one interface every hologram method implements, and the registry that finds methods by name.

A method is called as `method(target_amplitude, setup, *, iterations=None, seed=0, progress=None)` and returns a
float32 phase (H, W) in [-pi, pi). `Method` does what all methods share (input checks, iteration count, phase
wrapping) and hands the algorithm a clean target, so an algorithm (classical or learned) is only its maths.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral
from typing import Callable, Optional

import torch

from benchctl.errors import BadValueError
from benchctl.optics.setup import OpticalSetup

Progress = Callable[[int, int], None]
"""Called as progress(done, total) after each iteration of an iterative method."""

Algorithm = Callable[[torch.Tensor, OpticalSetup, Optional[int], int, Optional[Progress]], torch.Tensor]
"""algorithm(target, setup, iterations, seed, progress) -> phase (any real values; `Method` wraps them).

`target` is float32 (H, W), finite, >= 0, zero outside the ROI, scaled to max 1 (or all zero);
`iterations` is None for a one-shot method, else a resolved count >= 0.
"""

# Largest float32 below pi: phases are clamped to +-this so they lie in [-pi, pi) whether compared in float32
# (where float32(pi) > pi) or float64.
_PI_BELOW = float(torch.nextafter(torch.tensor(math.pi, dtype=torch.float32), torch.tensor(0.0)))


def wrap_phase(phase: torch.Tensor) -> torch.Tensor:
    """Wrap real phases to [-pi, pi) as float32 (computed in float64, so large unwrapped phases stay exact)."""
    wrapped = torch.remainder(phase.double() + math.pi, 2.0 * math.pi) - math.pi
    return wrapped.float().clamp(-_PI_BELOW, _PI_BELOW)


def check_target(target_amplitude: torch.Tensor, setup: OpticalSetup) -> torch.Tensor:
    """Validate a target amplitude for `setup` and return it as float32 scaled to max 1 (all-zero stays zero).

    Why scale: a phase-only hologram can only shape the light, not set its power, so only the amplitude's shape
    matters; one scale keeps every algorithm's numbers in the same range whatever units the caller used.
    """
    if not isinstance(target_amplitude, torch.Tensor):
        raise TypeError(f"target amplitude must be a torch.Tensor, got {type(target_amplitude).__name__}")
    if target_amplitude.dim() != 2:
        raise ValueError(f"target amplitude must be 2-D (H, W), got shape {tuple(target_amplitude.shape)}")
    if tuple(target_amplitude.shape) != setup.shape:
        raise ValueError(f"target amplitude is {tuple(target_amplitude.shape)}, the SLM grid is {setup.shape}")
    if target_amplitude.is_complex():
        raise ValueError("target amplitude must be real (an amplitude, not a complex field)")
    target = target_amplitude.detach().to(torch.float32)
    finite = torch.isfinite(target)
    if not bool(finite.all()):
        n_nan = int(torch.isnan(target).sum())
        n_inf = int((~finite).sum()) - n_nan
        raise ValueError(f"target amplitude must be finite: it has {n_nan} NaN and {n_inf} inf values "
                         "(after conversion to float32)")
    if bool((target < 0).any()):
        raise ValueError(f"target amplitude must be >= 0 (an amplitude, not a field); min is {float(target.min()):g}")
    rows, cols = setup.roi_slices
    outside = target.clone()
    outside[rows, cols] = 0
    if bool(outside.any()):
        raise ValueError(f"target amplitude must be zero outside the centred ROI {setup.roi} of the {setup.shape} "
                         "grid (pad the image with zeros to the grid)")
    peak = target.max()
    return target / torch.where(peak > 0, peak, torch.ones_like(peak))


@dataclass(frozen=True)
class Method:
    """A registered hologram method: a name, a one-line description, a default iteration count, an algorithm.

    `default_iterations` is None for one-shot methods (DPAC, a trained network's forward pass); those refuse an
    explicit `iterations` rather than silently ignoring it.
    """

    name: str
    description: str
    default_iterations: int | None
    algorithm: Algorithm

    def __call__(
        self,
        target_amplitude: torch.Tensor,
        setup: OpticalSetup,
        *,
        iterations: int | None = None,
        seed: int = 0,
        progress: Progress | None = None,
    ) -> torch.Tensor:
        """A phase-only hologram (H, W) float32 in [-pi, pi) whose reconstruction shows `target_amplitude`.

        Deterministic for a given seed; torch's global random state is left untouched.
        """
        target = check_target(target_amplitude, setup)
        if isinstance(seed, bool) or not isinstance(seed, Integral):
            raise BadValueError(f"seed must be an integer, got {seed!r}")
        phase = self.algorithm(target, setup, self._iterations(iterations), int(seed), progress)
        return wrap_phase(phase)

    def _iterations(self, iterations: int | None) -> int | None:
        if self.default_iterations is None:
            if iterations is not None:
                raise BadValueError(f"method {self.name!r} is one-shot and takes no iteration count (got {iterations})")
            return None
        if iterations is None:
            return self.default_iterations
        if isinstance(iterations, bool) or not isinstance(iterations, Integral) or iterations < 0:
            raise BadValueError(f"iterations must be an integer >= 0, got {iterations!r}")
        return int(iterations)


TOLERANCE = 1e-3
"""Default early stop of the iterative methods: relative fall of the best loss over STOP_WINDOW iterations."""
STOP_WINDOW = 20


def stopped_improving(losses: Sequence[float], tolerance: float, window: int = STOP_WINDOW) -> bool:
    """True once the best of `losses` fell by less than `tolerance` (relative) over the last `window` entries.

    `losses` is the loss history, one entry per iteration; a rising or flat tail counts as not improving,
    a still-falling one keeps going. Needs more than `window` entries to decide.
    """
    if len(losses) <= window:
        return False
    best_before = min(losses[:-window])
    best_now = min(best_before, min(losses[-window:]))
    return best_before - best_now <= tolerance * best_before


METHODS: dict[str, Method] = {}
"""Every registered method by name; add to it with `register`."""


def register(method: Method) -> Method:
    """Add `method` to `METHODS` (a name can be registered once) and return it."""
    if method.name in METHODS:
        raise ValueError(f"a hologram method named {method.name!r} is already registered")
    METHODS[method.name] = method
    return method


def method_names() -> list[str]:
    """Names of the registered methods, sorted."""
    return sorted(METHODS)


def get_method(name: str) -> Method:
    """The method registered as `name`; ValueError naming the known methods otherwise."""
    try:
        return METHODS[name]
    except (KeyError, TypeError):
        raise BadValueError(f"unknown hologram method {name!r}; known methods: {', '.join(method_names())}") from None
