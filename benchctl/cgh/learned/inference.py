"""Trained networks as hologram methods: `learned_method(name, checkpoint)` is a `Method` like DPAC or SGD.

A learned method is one-shot (one forward pass, no iteration count). It serves any optical setup that one of
the checkpoint's colours was trained for, exactly; any other setup is refused with the differences named.
`resolve_method` is what every caller that picks a method by name uses (generate, benchmarks, procedures):
classical names come from the registry; learned ones need a checkpoint, given or shipped for the profile.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import torch

from benchctl.cgh.learned.checkpoint import cached_checkpoint, cached_model, find_checkpoint, profile_setups
from benchctl.cgh.learned.models import LEARNED_METHODS, VARIANTS
from benchctl.cgh.method import Method, Progress, get_method
from benchctl.errors import BadValueError, BenchctlError
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile


def learned_method(name: str, checkpoint_path: Path | str) -> Method:
    """Method `name` with the trained models of `checkpoint_path` (which must hold a `name` checkpoint)."""
    path = Path(checkpoint_path)
    checkpoint = cached_checkpoint(path)
    if checkpoint.method != name:
        raise BadValueError(f"checkpoint {path} holds a {checkpoint.method} model, not {name}")

    def forward(target: torch.Tensor, setup: OpticalSetup, iterations: int | None, seed: int,
                progress: Progress | None) -> torch.Tensor:
        colour = cached_checkpoint(path).colour_for(setup)
        model = cached_model(path, colour, target.device)
        with torch.inference_mode():
            phase = model(target[None, None])[0, 0]
        if progress is not None:
            progress(1, 1)
        # a normal tensor, not an inference tensor, for callers that go on with autograd
        return setup.without_wavefront(phase.clone())

    family = VARIANTS[name].family
    return Method(name=name, description=f"trained {family} network ({path})", default_iterations=None,
                  algorithm=forward)


def resolve_method(name: str, profile: Profile, checkpoint: Path | str | None = None,
                   channels: Sequence[str] | None = None) -> tuple[Method, Path | None]:
    """The method to run for `name` on `profile`, and the checkpoint it uses (None for classical methods).

    Learned methods use `checkpoint`, else the one shipped for the profile (`find_checkpoint`), and must fit
    the geometry of the `channels` they will run for (all of the profile's by default). A classical method
    given a checkpoint is an error, as is a learned one with none.
    """
    if name not in LEARNED_METHODS:
        method = get_method(name)
        if checkpoint is not None:
            raise BadValueError(f"method {name!r} is not a learned method and takes no checkpoint "
                                f"(got --checkpoint {checkpoint})")
        return method, None
    path = Path(checkpoint) if checkpoint is not None else find_checkpoint(name, profile)
    if path is None:
        raise BenchctlError(f"no trained checkpoint for {name!r} and profile {profile.name!r}: train one with "
                            f"`benchctl train --method {name} --data DIR --profile {profile.name}` or pass "
                            "--checkpoint FILE")
    method = learned_method(name, path)
    cached_checkpoint(path).check(profile_setups(profile, channels), f"profile {profile.name!r}")
    return method, path
