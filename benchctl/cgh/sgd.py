"""Stochastic gradient descent on the SLM phase (Adam), fitting the simulated reconstruction to the target.

Loss: MSE over the ROI between s * |P_{+z}(exp(i phase))| and the target amplitude, with s the closed-form
least-squares scale sum(r t) / sum(r^2) of the current reconstruction (a phase-only hologram cannot set the
image's brightness). At that s the loss's gradient with respect to s is zero, so treating s as a constant in
the backward pass gives the exact gradient of the scale-free error; nothing about the scale is learned.

Choices (docs/benchmarks.md and docs/model_calibration.md measure them):
- Start from the DPAC hologram, not from neural-holography's uniform [-0.5, 0.5] phase: DPAC is already a
  good solution, so the first iterations refine it instead of building one from a flat phase.
  `init="random"` keeps that uniform start; `init` may also be any `Method` (a trained network's output).
- Adam with lr 0.05 on the phase (neural-holography: 8e-3, plus 2e-3 on a learned scale).
- Where the SLM cannot show every phase (`setup.display`: a measured lookup table whose levels leave a gap, such
  as red on a panel with 2 pi at 600 nm), the loss scores the phase as shown, its gradient passed straight
  through the quantisation; and after each step a phase in the table's gap, which that gradient cannot move out
  of, is set to the phase the SLM shows for it (`OpticalSetup.within_reach`).
- The best phase seen is returned, so SGD never ends worse (in its loss) than the phase it started from.
- Early stop: once the best loss fell by less than `tolerance` (relative) over the last `STOP_WINDOW`
  iterations, further iterations would change the result by less than that: stop and report the
  iterations done as the total (an all-black target stops after STOP_WINDOW iterations: its loss is zero).

A scene with depth (`FocalStackTarget`, two planes or more) is optimised the same way, on the focal-stack loss
(`stack_loss`: every plane scored where the scene is in focus there, Neural 3D Holography's masked loss) through
the same setup, so the fitted model and the lookup table apply as in 2D; it starts from the method DPAC makes of
the scene (layered, anti-aliased). A target with a sweep (a scene with continuous depth, `--planes auto`) is scored
at planes that move one step through its depths per iteration (`FocalStackTarget.swept`), each plane scoring the
pixels near its depth: each iteration's loss then sees another part of the scene, so there is no early stop and the
last phase is returned.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import torch

from benchctl.cgh.dpac import DPAC
from benchctl.cgh.method import TOLERANCE, Method, Progress, register, stopped_improving
from benchctl.errors import BadValueError
from benchctl.optics.focal_stack import FocalStackTarget, focal_stack_loss
from benchctl.optics.metrics import lsq_scale
from benchctl.optics.setup import OpticalSetup

DEFAULT_ITERATIONS = 500
PHASE_LR = 0.05
RANDOM_RANGE = 0.5  # init="random": phase uniform in [-RANDOM_RANGE, RANDOM_RANGE] rad (neural-holography's start)

Init = str | Method
INITS = ("dpac", "random")


def roi_loss(phase: torch.Tensor, target: torch.Tensor, setup: OpticalSetup) -> torch.Tensor:
    """MSE over the ROI between the least-squares-scaled reconstruction of `phase` as the SLM shows it
    (`setup.displayed`) and `target` (SLM grid).

    The scale is computed from the reconstruction but held constant for autograd (exact at the optimum).
    """
    rows, cols = setup.roi_slices
    recon = setup.reconstruct_roi(setup.displayed(phase))
    wanted = target[..., rows, cols]
    scale = lsq_scale(recon.detach(), wanted)
    return torch.nn.functional.mse_loss(scale * recon, wanted)


def stack_loss(phase: torch.Tensor, target: FocalStackTarget, setup: OpticalSetup,
               iteration: int | None = None) -> torch.Tensor:
    """The focal-stack loss (`focal_stack_loss`) over the ROI of the planes of `target`, reconstructed from `phase`
    as the SLM shows it (`setup.displayed`) through one multi-plane propagation; with an `iteration`, at the planes
    of the target's sweep there (`FocalStackTarget.swept`)."""
    rows, cols = setup.roi_slices
    if iteration is None or target.sweep is None:
        recon = setup.reconstruct_planes_roi(setup.displayed(phase), target.planes_m)
        masks = target.masks[:, rows, cols]
    else:
        pick, masks = target.swept(iteration, (rows, cols))
        recon = setup.reconstruct_planes_roi(setup.displayed(phase), target.sweep.all_m, pick)
    return focal_stack_loss(recon, target.amplitude[rows, cols], masks.to(recon.device))


def _initial_phase(init: Init, target: torch.Tensor | FocalStackTarget, setup: OpticalSetup,
                   seed: int) -> torch.Tensor:
    if isinstance(init, Method):
        return init(target, setup, seed=seed)
    if init == "dpac":
        return DPAC(target, setup)
    amplitude = target.amplitude if isinstance(target, FocalStackTarget) else target
    generator = torch.Generator(device=amplitude.device).manual_seed(seed)
    return (torch.rand(amplitude.shape, generator=generator, device=amplitude.device) * 2 - 1) * RANDOM_RANGE


def _descend(loss_of: Callable[[torch.Tensor], torch.Tensor], start: torch.Tensor, setup: OpticalSetup,
             iterations: int, lr: float, tolerance: float | None, progress: Progress | None, *,
             sampled: bool = False) -> torch.Tensor:
    """Adam on the phase from `start`, minimising `loss_of(phase)`: the best phase seen (module docstring); where the
    loss is `sampled` (each call scores another part of the target), the last one, after every iteration."""
    phase = start.detach().clone().requires_grad_()
    optimiser = torch.optim.Adam([phase], lr=lr)
    losses: list[float] = []
    best_loss, best_phase = float("inf"), phase.detach().clone()
    for done in range(iterations + 1):
        if sampled and done == iterations:
            return phase.detach()
        optimiser.zero_grad(set_to_none=True)
        loss = loss_of(phase)
        if not sampled:  # a sampled loss is not comparable between iterations: no best phase, no early stop
            losses.append(float(loss.detach()))
            if losses[-1] < best_loss:
                best_loss, best_phase = losses[-1], phase.detach().clone()
            if done == iterations:
                break  # the loss of the last step's phase is known: no further step
            if tolerance is not None and stopped_improving(losses, tolerance):
                if progress is not None:
                    progress(done, done)
                break
        loss.backward()
        optimiser.step()
        with torch.no_grad():
            phase.copy_(setup.within_reach(phase))
        if progress is not None:
            progress(done + 1, iterations)
    return best_phase


def sgd_method(name: str = "sgd", *, init: Init = "dpac", lr: float = PHASE_LR,
               tolerance: float | None = TOLERANCE, description: str | None = None) -> Method:
    """An SGD `Method` starting from `init` ("dpac", "random" or a `Method`), Adam at `lr`, early stop at
    `tolerance` (None: always run the full budget). Not registered: `register` it to find it by name."""
    if not isinstance(init, Method) and init not in INITS:
        raise BadValueError(f"SGD init must be one of {', '.join(INITS)} or a Method, got {init!r}")
    if not lr > 0:
        raise BadValueError(f"SGD learning rate must be > 0, got {lr!r}")
    if tolerance is not None and not tolerance >= 0:
        raise BadValueError(f"SGD tolerance must be >= 0 or None, got {tolerance!r}")
    start = init.name if isinstance(init, Method) else init

    def algorithm(target: torch.Tensor, setup: OpticalSetup, iterations: int | None, seed: int,
                  progress: Progress | None) -> torch.Tensor:
        assert iterations is not None  # Method resolves the default for iterative methods
        # Optimise even when called under no_grad or inference_mode; the clone makes the target a normal tensor.
        with torch.inference_mode(False), torch.enable_grad():
            target = target.clone()
            start = _initial_phase(init, target, setup, seed)
            return _descend(lambda phase: roi_loss(phase, target, setup), start, setup, iterations, lr, tolerance,
                            progress)

    def focal_stack(target: FocalStackTarget, setup: OpticalSetup, iterations: int | None, seed: int,
                    progress: Progress | None) -> torch.Tensor:
        assert iterations is not None
        with torch.inference_mode(False), torch.enable_grad():
            target = target.with_amplitude(target.amplitude.clone())
            start = _initial_phase(init, target, setup, seed)
            steps = itertools.count()
            return _descend(lambda phase: stack_loss(phase, target, setup, next(steps)), start, setup, iterations,
                            lr, tolerance, progress, sampled=target.sweep is not None)

    return Method(name=name, default_iterations=DEFAULT_ITERATIONS, algorithm=algorithm, focal_stack=focal_stack,
                  description=description or f"Adam on the SLM phase from a {start} start, minimising the simulated "
                                             "ROI error (of a scene with depth: its focal stack's in-focus error), "
                                             "stopping once it stops improving")


SGD = register(sgd_method())
