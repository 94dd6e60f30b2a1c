"""`benchctl train`: the training of `benchctl.cgh.learned.training` for a hardware profile, with a summary."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from benchctl.cgh.learned.training import TrainResult, TrainSettings, train
from benchctl.profiles import Profile
from benchctl.runner.holograms import target_plane


def run_train(profile: Profile, settings: TrainSettings, out_dir: Path, *, resume: Path | None = None,
              out: Callable[[str], None] = print) -> TrainResult:
    """Train one model per colour of `profile` (each on the image plane its laser displays, as in
    `benchctl generate`), write checkpoints to `out_dir` and print where they are and what they reach."""
    profile.require("slm", "optics", "laser")
    planes = {channel.name: target_plane(channel) for channel in profile.channels}
    result = train(profile, settings, out_dir, planes, resume=resume, out=out)
    if result.rank != 0:
        return result
    if result.checkpoint is None:
        out(f"nothing to train: the run already stands at {settings.epochs} epoch(s) / its --max-steps")
        return result
    for colour, metrics in result.metrics.items():
        scores = (f"validation PSNR {metrics['val_psnr_amplitude_db']:.2f} dB amplitude, SSIM "
                  f"{metrics['val_ssim_amplitude']:.3f}" if "val_psnr_amplitude_db" in metrics
                  else "no validation images")
        out(f"{colour:>6}: {scores} (training loss {metrics['train_loss']:.5f})")
    out(f"{result.steps} step(s), {result.epochs_done} complete epoch(s); checkpoint {result.checkpoint}")
    return result
