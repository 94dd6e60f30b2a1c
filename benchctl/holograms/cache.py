"""Holograms computed once per target, method and geometry, and reused by later runs.

The key is a hash of everything the displayed frame depends on: the target plane's amplitude, the method and
its options (iterations, seed, checkpoint file contents), the channel's optical setup (its geometry fingerprint,
`Geometry.to_dict`, and fitted model) and the SLM encoding (bit depth, lookup table, offset, carrier, flips),
plus a hash of benchctl's source, so an edited method never reuses holograms the old code made. An entry holds the
frame as displayed, the simulated reconstruction and its scores, and the seconds it took to compute. A scene with depth
is keyed by its depth map and planes too; its entry holds the simulated focal stack and per-plane scores.
Entries live in $BENCHCTL_CACHE_DIR/holograms (default ~/.cache/benchctl/holograms); deleting them is safe.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from benchctl.calibration.calibrated import Calibrated
from benchctl.cgh import get_method
from benchctl.files import atomic_write_bytes, ensure_dir
from benchctl.holograms.checkpoints import find_checkpoint
from benchctl.holograms.depth import compute_depth_scene
from benchctl.holograms.scene import compute_scene
from benchctl.optics.planes import PlaneChoice
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile
from benchctl.provenance import source_hash
from benchctl.targets import target_plane

CACHE_ENV = "BENCHCTL_CACHE_DIR"


@dataclass(frozen=True)
class Hologram:
    """One colour's hologram: the frame as displayed, its simulated reconstruction (ROI amplitude, scaled to
    the target; of a scene with depth, its focal stack (K, h, w)), the scores of that reconstruction (of a focal
    stack, their means over the planes, and `plane_scores` per plane), and how long generating it took."""

    gray: np.ndarray
    reconstruction: np.ndarray
    scores: dict[str, float]
    seconds: float
    cached: bool
    plane_scores: list[dict[str, float] | None] | None = None


def cache_dir() -> Path:
    root = os.environ.get(CACHE_ENV)
    return Path(root) if root else Path.home() / ".cache" / "benchctl"


def _key(profile: Profile, setup: OpticalSetup, channel: str, plane: torch.Tensor, options: dict[str, Any],
         depth_m: torch.Tensor | None = None) -> str:
    slm = profile.slm
    assert slm is not None
    digest = hashlib.sha256()
    description = {
        "code": source_hash(), "options": options, "geometry": setup.geometry.to_dict(), "bit_depth": slm.bit_depth,
        "two_pi_gray": slm.two_pi_gray, "offset": slm.phase_offset_rad, "carrier": list(slm.grating_period_px),
        "flips": [slm.flip_y, slm.flip_x],
        "field_model": setup.field_model.to_dict() if setup.field_model else None,
    }
    digest.update(json.dumps(description, sort_keys=True, default=str).encode())
    for path in (slm.lut.get(channel), options.get("checkpoint")):
        if path:
            digest.update(Path(path).read_bytes())
    digest.update(plane.contiguous().numpy().tobytes())
    if depth_m is not None:
        digest.update(depth_m.to(torch.float64).contiguous().numpy().tobytes())
    return digest.hexdigest()[:32]


def cache_entry(bench: Calibrated, target: torch.Tensor, channel: str, method: str, *, iterations: int | None,
                seed: int, checkpoint: str | None, depth_m: torch.Tensor | None = None,
                planes: PlaneChoice | None = None) -> tuple[Path, str | None]:
    """Where the hologram of `channel` for `target` with these options is cached, and the checkpoint it is computed
    with: the one given, else the one found for a learned method (or for a refined one's network: "ccnn-dcm4+sgd"
    runs ccnn-dcm4's). That checkpoint's bytes are part of the key, as are the code, the bench and the target (of a
    scene with depth, its depth map, the planes it is shown at and their sweep)."""
    network = get_method(method).network
    if checkpoint is None and network is not None:
        found = find_checkpoint(network, bench.profile)  # what compute_scene will use
        checkpoint = str(found) if found else None
    options: dict[str, Any] = {"method": method, "iterations": iterations, "seed": seed, "checkpoint": checkpoint}
    if depth_m is not None:
        if planes is None:
            raise ValueError("a scene with depth needs the planes it is shown at")
        options["planes_m"] = [float(z) for z in planes.planes_m]
        if planes.sweep is not None:
            options["sweep"] = {"depths_m": planes.sweep.depths_m, "reach_m": planes.sweep.reach_m}
    plane = target[target_plane(bench.profile.channel(channel))]
    key = _key(bench.profile, bench.setup(channel), channel, plane, options, depth_m)
    return cache_dir() / "holograms" / f"{key}.npz", checkpoint


def hologram(bench: Calibrated, target: torch.Tensor, channel: str, method: str, *, iterations: int | None,
             seed: int, checkpoint: str | None,
             progress: Callable[[str], Callable[[int, int], None]] | None = None,
             depth_m: torch.Tensor | None = None, planes: PlaneChoice | None = None) -> Hologram:
    """The hologram of `channel` for `target` (3, H, W amplitude on the SLM grid) on `bench`: from the cache when
    this exact computation was done before (`cache_entry`), else computed (compute_scene, one colour) and cached.
    With `depth_m` (H, W, metres from the SLM) the target is a scene with depth shown at `planes`
    (compute_depth_scene, one colour, at exactly those planes and their sweep)."""
    path, checkpoint = cache_entry(bench, target, channel, method, iterations=iterations, seed=seed,
                                   checkpoint=checkpoint, depth_m=depth_m, planes=planes)
    if path.is_file():
        with np.load(path, allow_pickle=False) as data:
            return Hologram(data["gray"], data["reconstruction"], json.loads(str(data["scores"])),
                            float(data["seconds"]), cached=True,
                            plane_scores=json.loads(str(data["plane_scores"])))
    chosen = Path(checkpoint) if checkpoint else None
    if depth_m is None:
        result = compute_scene(target, bench, method, iterations=iterations, colours=[channel], seed=seed,
                               progress=progress, checkpoint=chosen).colours[0]
    else:
        result = compute_depth_scene(target, depth_m, bench, method, planes=planes, iterations=iterations,
                                     colours=[channel], seed=seed, progress=progress, perceptual=False,
                                     checkpoint=chosen).colours[0]
    assert not result.skipped and result.gray is not None and result.reconstruction is not None
    entry = Hologram(result.gray, result.reconstruction.numpy(), result.scores, result.seconds, cached=False,
                     plane_scores=result.plane_scores if depth_m is not None else None)
    buffer = io.BytesIO()
    np.savez(buffer, gray=entry.gray, reconstruction=entry.reconstruction, scores=json.dumps(entry.scores),
             seconds=entry.seconds, plane_scores=json.dumps(entry.plane_scores))
    ensure_dir(path.parent)
    atomic_write_bytes(path, buffer.getvalue())
    return entry
