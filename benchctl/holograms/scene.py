"""Holograms for a colour scene: one method per emitting colour, displayed phase, simulated reconstruction, scores.

This is the in-memory core shared by `benchctl generate` and `benchctl bench speed-vs-error`; it writes no files.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from benchctl.calibration.calibrated import Calibrated
from benchctl.capture.colour_planes import merge_colours
from benchctl.cgh import Method, get_method, method_names
from benchctl.cgh.learned import DEPTH_METHODS, LEARNED_METHODS, model_info
from benchctl.errors import BadValueError, BenchctlError
from benchctl.holograms.checkpoint_notes import checkpoint_notes
from benchctl.holograms.checkpoints import (
    cached_checkpoint,
    checkpoint_problem,
    find_checkpoint,
    learned_method,
    profile_geometries,
)
from benchctl.optics import amplitude_scores, colour_scores, crop_roi
from benchctl.profiles import LaserChannel, Profile
from benchctl.targets import active_channels, target_plane


@dataclass
class ColourResult:
    """One colour: skipped (black in the target) or its displayed hologram, reconstruction and scores."""

    channel: str
    wavelength_nm: float
    skipped: bool
    seconds: float = 0.0
    gray: np.ndarray | None = None  # the SLM frame exactly as displayed (lookup table, offset, carrier, flips)
    reconstruction: torch.Tensor | None = None  # ROI amplitude (h, w) or focal stack (K, h, w), least-squares scaled
    scores: dict[str, float] = field(default_factory=dict)  # a scene with depth: the means over its planes
    plane_scores: list[dict[str, float] | None] = field(default_factory=list)  # a scene with depth: per plane


@dataclass
class SceneResult:
    """All colours of one target plus the merged colour image (linear RGB on the ROI) and its scores."""

    method: str
    iterations: int | None
    colours: list[ColourResult]
    target_roi: torch.Tensor  # (3, h, w) amplitude
    merged_linear: torch.Tensor  # (3, h, w) linear intensity
    merged_scores: dict[str, float]
    checkpoint: Path | None = None  # the trained models a learned method used


def checkpoint_status(method: str, profile: Profile) -> str:
    """Where the trained checkpoint that `method` runs for `profile` is, or why there is none it can use."""
    network = get_method(method).network
    if network is None:
        return "needs no checkpoint"
    path = find_checkpoint(network, profile)
    if path is None:
        return f"no trained checkpoint for profile {profile.name!r}"
    problem = checkpoint_problem(path, profile)
    if problem is not None:
        return f"{path} does not fit: {problem}"
    return "; ".join([str(path), *checkpoint_notes(cached_checkpoint(path).metadata(), profile)])


def usable_methods(profile: Profile) -> list[str]:
    """The registered methods that run out of the box for `profile`, in `method_names` order: the classical
    ones, and those whose network has a checkpoint found for `profile` that fits its geometry."""
    fits: dict[str, bool] = {}
    for name in LEARNED_METHODS:
        path = find_checkpoint(name, profile)
        fits[name] = path is not None and checkpoint_problem(path, profile) is None
    return [name for name in method_names() if (network := get_method(name).network) is None or fits[network]]


def list_methods(shape: tuple[int, int], profile: Profile | None = None) -> list[str]:
    """Every hologram method: family, trainable parameters at `shape`, and whether it can run now.

    Methods that need a checkpoint (learned ones and their SGD refinements) need a trained one that fits the
    profile's geometry; the last column says where it is or why there is none (without a profile: that a
    checkpoint is needed).
    """
    lines = [f"{'method':<24} {'family':<10} {'parameters':>11}  usable / checkpoint"]
    usable = usable_methods(profile) if profile is not None else []
    for name in method_names():
        method = get_method(name)
        if method.network is None:
            lines.append(f"{name:<24} {method.family:<10} {'-':>11}  yes ({method.description})")
            continue
        parameters = model_info(method.network, shape)["parameters"]
        status = checkpoint_status(name, profile) if profile is not None else "needs a trained checkpoint"
        state = "yes" if name in usable else "no"
        lines.append(f"{name:<24} {method.family:<10} {parameters:>11,}  {state} ({status})")
    return lines


def resolve_method(name: str, profile: Profile, checkpoint: Path | str | None = None,
                   channels: Sequence[str] | None = None) -> tuple[Method, Path | None]:
    """The runnable method for `name` on `profile`, and the checkpoint it uses (None for classical methods).

    What every caller that picks a method by name uses (generate, the cache, benchmarks, procedures). A method
    that needs a checkpoint uses `checkpoint`, else the one shipped for the profile (`find_checkpoint`), and
    must fit the geometry of the `channels` it will run for (all of the profile's by default). An unknown name
    is an error listing the known ones; a classical method given a checkpoint is an error, as is a learned one
    with none.
    """
    method = get_method(name)
    if method.network is None:
        if checkpoint is not None:
            raise BadValueError(f"method {name!r} is not a learned method and takes no checkpoint "
                                f"(got --checkpoint {checkpoint})")
        return method, None
    path = Path(checkpoint) if checkpoint is not None else find_checkpoint(method.network, profile)
    if path is None:
        data = "procedural-rgbd:1024" if method.network in DEPTH_METHODS else "DIR"
        raise BenchctlError(f"no trained checkpoint for {method.network!r} and profile {profile.name!r}: train one "
                            f"with `benchctl train --method {method.network} --data {data} --profile {profile.name}` "
                            "or pass --checkpoint FILE")
    runnable = learned_method(name, path)
    cached_checkpoint(path).check(profile_geometries(profile, channels), f"profile {profile.name!r}")
    return runnable, path


def select_channels(profile: Profile, names: list[str] | None) -> list[LaserChannel]:
    """The profile's channels in profile order, or the named ones (unknown names are an error)."""
    if not names:
        return list(profile.channels)
    return [profile.channel(name) for name in names]


def compute_scene(
    target_amplitude: torch.Tensor,
    bench: Calibrated,
    method: str,
    *,
    iterations: int | None = None,
    colours: list[str] | None = None,
    seed: int = 0,
    progress: Callable[[str], Callable[[int, int], None]] | None = None,
    checkpoint: Path | None = None,
) -> SceneResult:
    """Generate, quantise, display (in simulation) and score a hologram for each requested, non-black colour.

    `target_amplitude` is (3, H, W) on the SLM grid (see `benchctl.targets.prepare_target`). `progress`, if
    given, is called with a label per colour and returns that colour's `(done, total)` callback. A learned
    method uses `checkpoint`, else the checkpoint shipped for the profile (`find_checkpoint`); it is refused
    (BenchctlError) when there is none or when it was trained for another geometry; a classical method given
    a checkpoint is an error too. Each colour is computed and simulated on `bench`'s optical setup, through its
    SLM's lookup tables.
    """
    profile = bench.profile
    grid, roi = profile.section("slm").shape, profile.section("optics").roi
    if tuple(target_amplitude.shape) != (3, *grid):
        raise BenchctlError(f"target is {tuple(target_amplitude.shape)}, the SLM grid needs (3, {grid[0]}, {grid[1]})")
    present = active_channels(target_amplitude)
    channels = select_channels(profile, colours)
    generate, used_checkpoint = resolve_method(method, profile, checkpoint,
                                               [c.name for c in channels if present[target_plane(c)]])
    slm = bench.slm
    target_roi = crop_roi(target_amplitude, roi)
    lit = [channel for channel in channels if present[target_plane(channel)]]
    computed: dict[str, tuple[float, np.ndarray, torch.Tensor]] = {}
    for channel in lit:
        setup = bench.setup(channel.name, as_displayed=True)
        start = time.perf_counter()
        phase = generate(target_amplitude[target_plane(channel)], setup, iterations=iterations, seed=seed,
                         progress=progress(f"{method} {channel.name}") if progress else None)
        seconds = time.perf_counter() - start
        gray = slm.encode(phase, channel.name)
        computed[channel.name] = seconds, gray, setup.reconstruct_roi(torch.from_numpy(slm.driven(gray, channel.name)))
    merged = merge_colours({target_plane(c): computed[c.name][2] for c in lit}, target_roi)
    results = []
    for channel in channels:
        plane = target_plane(channel)
        if channel.name not in computed:
            results.append(ColourResult(channel.name, channel.wavelength_nm, skipped=True))
            continue
        seconds, gray, _ = computed[channel.name]
        recon = merged.amplitude[plane]
        results.append(ColourResult(channel.name, channel.wavelength_nm, skipped=False, seconds=seconds,
                                    gray=gray, reconstruction=recon, scores=amplitude_scores(recon, target_roi[plane])))
    # the colour scores cover the planes computed: a --colours subset is not penalised for the planes it left out
    chosen = torch.zeros(3, 1, 1, dtype=target_roi.dtype)
    chosen[[target_plane(channel) for channel in channels]] = 1
    return SceneResult(method, iterations, results, target_roi, merged.linear,
                       colour_scores(merged.linear, target_roi * chosen), checkpoint=used_checkpoint)
