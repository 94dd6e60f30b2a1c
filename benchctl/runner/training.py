"""`benchctl train`: the training of `benchctl.cgh.learned.training` for a hardware profile, with a summary."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from msgspec.structs import replace

from benchctl.cgh.learned.training import TrainResult, TrainSettings, train
from benchctl.errors import BadValueError, BenchctlError
from benchctl.optics.fitted import FittedOptics
from benchctl.profiles import Profile
from benchctl.runner.calibration import Calibration
from benchctl.runner.holograms import target_plane


def run_train(profile: Profile, settings: TrainSettings, out_dir: Path, *, resume: Path | None = None,
              out: Callable[[str], None] = print) -> TrainResult:
    """Train one model per colour of `profile` (each on the image plane its laser displays, as in
    `benchctl generate`), write checkpoints to `out_dir` and print where they are and what they reach."""
    profile = with_model_calibration(profile.require("slm", "optics", "laser"), settings)
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


def with_model_calibration(profile: Profile, settings: TrainSettings) -> Profile:
    """`profile` carrying the fitted optical model `--model-calibration` names ("stored": the profile's, from model
    calibration; else an optical-model.json), checked to hold a model for every colour trained, on the profile's
    own grid; `profile` itself without the option."""
    how = settings.model_calibration
    if how is None:
        return profile
    flag = f"--model-calibration {how}"
    if settings.size is not None:
        raise BadValueError(f"{flag}: the model was fitted on the profile's {profile.slm.height}x{profile.slm.width} "
                            "grid; train on that grid (leave out --size)")
    if how == "stored":
        calibrated = Calibration.store(profile).with_model(replace(profile, optics=replace(profile.optics,
                                                                                              model=None)))
        if calibrated.optics.model is None:
            raise BenchctlError(f"{flag}: no fitted optical model is stored for profile {profile.name!r}; run "
                                "procedures/model_calibration.toml first, or name an optical-model.json")
    else:
        path = Path(how).expanduser()
        if not path.is_file():
            raise BadValueError(f"{flag}: no such file")
        calibrated = replace(profile, optics=replace(profile.optics, model=path.resolve()))
    for name in settings.colours or [channel.name for channel in profile.channels]:
        try:
            model = FittedOptics.load(calibrated.optics.model, profile.channel(name).name)
        except (ValueError, KeyError, TypeError) as exc:
            raise BadValueError(f"{flag}: {calibrated.optics.model} is not an optical model file ({exc})") from None
        if model is None:
            raise BadValueError(f"{flag}: {calibrated.optics.model} has no fitted model for {name!r}")
    return calibrated
