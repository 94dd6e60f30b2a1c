"""The one interface every hologram method implements, and the one registry that finds methods by name.

A method is called as `method(target_amplitude, setup, *, iterations=None, seed=0, progress=None)` and returns a
float32 phase (H, W) in [-pi, pi). `Method` does what all methods share (input checks, iteration count, phase
wrapping) and hands the algorithm a clean target, so an algorithm (classical or learned) is only its maths.

The target may also be a scene with depth (`FocalStackTarget`: amplitude, depth and the planes it is shown at). A
method with a `focal_stack` algorithm makes its hologram for all the planes at once; a scene on one plane is a flat
scene, and every method makes it as its 2D algorithm makes a 2D target at that plane's distance (the same
hologram, at the same cost).

The registry holds every method: classical ones, learned ones (a method that needs trained networks, from a
checkpoint: `needs_checkpoint`) and learned ones refined by SGD (`<learned>+sgd`, composed from the learned
one). A method that needs a checkpoint runs once `trained` gives it its networks; where those come from
(checkpoint files, profiles) is the runner's business, not this layer's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral
from typing import Callable, Optional

import torch

from benchctl.errors import BadValueError, did_you_mean
from benchctl.optics.focal_stack import FocalStackTarget
from benchctl.optics.setup import OpticalSetup

Progress = Callable[[int, int], None]
"""Called as progress(done, total) after each iteration of an iterative method."""

Algorithm = Callable[[torch.Tensor, OpticalSetup, Optional[int], int, Optional[Progress]], torch.Tensor]
"""algorithm(target, setup, iterations, seed, progress) -> phase (any real values; `Method` wraps them).

`target` is float32 (H, W), finite, >= 0, zero outside the ROI, scaled to max 1 (or all zero);
`iterations` is None for a one-shot method, else a resolved count >= 0.
"""

FocalStackAlgorithm = Callable[[FocalStackTarget, OpticalSetup, Optional[int], int, Optional[Progress]],
                               torch.Tensor]
"""focal_stack(target, setup, iterations, seed, progress) -> phase, for a scene with depth on two planes or more (a
method that `reads_depth`: on any number of planes).

`target.amplitude` is checked and scaled as `Algorithm`'s target is; `target.planes_m` are the planes' distances.
"""

Networks = Callable[[OpticalSetup, torch.device], Callable[..., torch.Tensor]]
"""networks(setup, device) -> the trained network for `setup` on `device`: amplitude (B, 1, H, W) (and, for a
network that reads depth, the depth (B, 1, H, W) metres) -> phase."""

DEFAULT_METHOD = "dpac"
"""The method used wherever none is named (generate, procedures): one-shot, no checkpoint needed."""

REFINED_SUFFIX = "+sgd"
"""`<learned method>+sgd`: that network's hologram refined by SGD, an iterative method of its own."""

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
    explicit `iterations` rather than silently ignoring it. `family` is "classical" or the learned network's
    family; a learned method has no algorithm until `trained` binds its networks, and a refined one names the
    learned method it starts from in `refines`. `focal_stack`, where given, makes holograms of scenes with depth.
    A learned method that `reads_depth` (a network for scenes with depth) makes them from the image and its depth
    map in one forward pass, on one plane too (its network knows the depth range, not one plane's distance).
    """

    name: str
    description: str
    default_iterations: int | None
    algorithm: Algorithm | None
    family: str = "classical"
    refines: str | None = None
    focal_stack: FocalStackAlgorithm | None = None
    reads_depth: bool = False

    @property
    def needs_checkpoint(self) -> bool:
        """True for learned and refined methods: they run only with trained networks (see `trained`)."""
        return self.algorithm is None

    @property
    def network(self) -> str | None:
        """The learned method whose checkpoint this method runs (itself or the one it refines); None if classical."""
        return (self.refines or self.name) if self.needs_checkpoint else None

    def trained(self, networks: Networks, source: str) -> Method:
        """This learned (or refined) method running `networks`, trained as `source` says (e.g. a checkpoint path).

        A learned method is one-shot: one forward pass of the network trained for the setup it is called with.
        A refined method is SGD started from that learned method's hologram.
        """
        if not self.needs_checkpoint:
            raise BadValueError(f"method {self.name!r} is not a learned method and takes no trained networks")
        if self.refines is not None:
            from benchctl.cgh.sgd import sgd_method  # sgd builds on this module

            return sgd_method(self.name, init=get_method(self.refines).trained(networks, source),
                              description=self.description)

        def forward(target: torch.Tensor, setup: OpticalSetup, iterations: int | None, seed: int,
                    progress: Progress | None) -> torch.Tensor:
            model = networks(setup, target.device)
            with torch.inference_mode():
                phase = model(target[None, None])[0, 0]
            if progress is not None:
                progress(1, 1)
            # a normal tensor, not an inference tensor, for callers that go on with autograd
            return setup.without_wavefront(phase.clone())

        def forward_in_depth(target: FocalStackTarget, setup: OpticalSetup, iterations: int | None, seed: int,
                             progress: Progress | None) -> torch.Tensor:
            model = networks(setup, target.amplitude.device)
            near, far = getattr(model, "depth_range_m", (0.0, math.inf))
            low, high = float(target.depth_m.min()), float(target.depth_m.max())
            if low < near * (1 - 1e-6) or high > far * (1 + 1e-6):
                raise BadValueError(f"the scene's depth {low * 1e3:.4g} .. {high * 1e3:.4g} mm lies outside the "
                                    f"{near * 1e3:.4g} .. {far * 1e3:.4g} mm {self.name} was trained for ({source})")
            with torch.inference_mode():
                phase = model(target.amplitude[None, None], target.depth_m[None, None])[0, 0]
            if progress is not None:
                progress(1, 1)
            return setup.without_wavefront(phase.clone())

        return Method(self.name, f"{self.description} ({source})", None, forward, self.family,
                      focal_stack=forward_in_depth if self.reads_depth else None, reads_depth=self.reads_depth)

    def __call__(
        self,
        target_amplitude: torch.Tensor | FocalStackTarget,
        setup: OpticalSetup,
        *,
        iterations: int | None = None,
        seed: int = 0,
        progress: Progress | None = None,
    ) -> torch.Tensor:
        """A phase-only hologram (H, W) float32 in [-pi, pi) whose reconstruction shows `target_amplitude`: an
        amplitude (H, W) at the setup's distance, or a scene with depth at its planes (`FocalStackTarget`).

        Deterministic for a given seed; torch's global random state is left untouched.
        """
        if isinstance(target_amplitude, FocalStackTarget):
            return self._focal_stack(target_amplitude, setup, iterations, seed, progress)
        if self.algorithm is None:
            raise BadValueError(f"method {self.name!r} needs trained networks: a checkpoint (`benchctl train`)")
        target = check_target(target_amplitude, setup)
        if isinstance(seed, bool) or not isinstance(seed, Integral):
            raise BadValueError(f"seed must be an integer, got {seed!r}")
        phase = self.algorithm(target, setup, self._iterations(iterations), int(seed), progress)
        return wrap_phase(phase)

    def _focal_stack(self, target: FocalStackTarget, setup: OpticalSetup, iterations: int | None, seed: int,
                     progress: Progress | None) -> torch.Tensor:
        """The hologram of a scene with depth: one plane is 2D at that plane's distance (unless the method reads
        depth); more need `focal_stack`."""
        if len(target.planes_m) == 1 and not self.reads_depth:
            return self(target.amplitude, setup.at_distance(target.planes_m[0]), iterations=iterations, seed=seed,
                        progress=progress)
        if self.focal_stack is None:
            if self.reads_depth:
                raise BadValueError(f"method {self.name!r} needs trained networks: a checkpoint (`benchctl train`)")
            able = [name for name in method_names()
                    if METHODS[name].focal_stack is not None or METHODS[name].reads_depth]
            raise BadValueError(f"method {self.name!r} makes holograms of one plane; a scene on "
                                f"{len(target.planes_m)} planes needs one of: {', '.join(able)}")
        if isinstance(seed, bool) or not isinstance(seed, Integral):
            raise BadValueError(f"seed must be an integer, got {seed!r}")
        checked = target.with_amplitude(check_target(target.amplitude, setup))
        return wrap_phase(self.focal_stack(checked, setup, self._iterations(iterations), int(seed), progress))

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
    """Names of the registered methods: classical ones sorted, then learned ones and their refinements in
    registration order."""
    classical = sorted(name for name, method in METHODS.items() if not method.needs_checkpoint)
    return classical + [name for name, method in METHODS.items() if method.needs_checkpoint]


def get_method(name: str) -> Method:
    """The method registered as `name`; BadValueError naming the known methods otherwise."""
    try:
        return METHODS[name]
    except (KeyError, TypeError):
        pass
    classical = [n for n in method_names() if not METHODS[n].needs_checkpoint]
    learned = [n for n in method_names() if METHODS[n].needs_checkpoint and METHODS[n].refines is None]
    raise BadValueError(f"unknown hologram method {name!r}{did_you_mean(name, METHODS)}; known: "
                        f"{', '.join(classical)}; learned (need a "
                        f"checkpoint): {', '.join(learned) or 'none'}; a learned one refined by SGD: "
                        f"<learned>{REFINED_SUFFIX}") from None
