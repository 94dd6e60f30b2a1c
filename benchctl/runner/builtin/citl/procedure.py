"""Camera-in-the-loop (CITL) optimisation (Peng et al. 2020): per colour, start from a model hologram (DPAC or SGD),
then each iteration displays the phase, captures RAW frames, decodes them, registers the colour's CFA plane onto
the target's ROI with the stored registration, and takes one Adam step on the phase with the straight-through
gradient (cgh.citl): the loss is the captured amplitude's error, differentiated through the propagation model (the
fitted optical model from calibration/<profile>/ when there is one, as SGD uses it).

Each iteration is one resumable step. It reads the phase and the optimiser state the previous one saved
(state/<colour>/<k>.npz, float32 as optimised) and saves the next, so a resumed run continues bit for bit; the
state two iterations back is deleted. Each state file's SHA-256 is in the result of the step that wrote it and is
checked before use: a damaged one (missing, truncated, edited, of another shape, pickled) sends the run back to the
step that wrote it, which recomputes it from its own state (or, that one gone too, from further back).

Divergence stops the run: a phase that is no longer finite after a step, or a captured loss above DIVERGENCE times
iteration 0's. A resume then goes back one iteration and continues from the last good phase at half the learning
rate (each state file carries the rate's scale).

Disk: the RAW frames (and the displayed SLM frame) are kept for the first and last iterations and every
`keep_raw_every`-th; every iteration keeps its registered plane as a 16-bit PNG on the ROI
(images/citl/<colour>/<k>.png). Iteration k records the loss and captured PSNR of phase k (the one it displayed) and
the seconds spent per stage; the last (k = iterations) only captures the final phase.

The learning rate falls from `learning_rate` to 0 over the iterations (cosine; `schedule = "constant"` keeps it):
late gradients are mostly camera noise, and constant steps then walk the phase away from its best.

The model is only the gradient's: where the bench departs far from it (the aberrated simulated bench without a
fitted model) the gradient points elsewhere and the captured PSNR rises for a few iterations, then falls; run
model calibration first (README, "Camera in the loop").

With `exposure = "auto"` (default) one probe frame of the start hologram per colour sets the laser power that
puts its peak at `peak_goal` of full scale; every iteration and the baseline are captured at that power.

The gradient runs where `device` says: "auto" (default) takes a CUDA GPU when torch sees one, else the CPU. At
full size on a 2-core CPU the gradient (0.3-0.5 s, four FFTs of the ROI's padded grid) is most of an iteration's
software time, and the part a GPU speeds up; decoding and registering stay on the CPU. A run resumed on another
device continues from the saved state, equal to float32 rounding rather than bit for bit.

With `baseline` (default on), model-only SGD with the same number of Adam steps (start_iterations + iterations
for an SGD start) is captured the same way, so the report compares both at one budget.
"""

from __future__ import annotations

import hashlib
import io
import math
import time
import zipfile
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch
from msgspec import Meta

from benchctl.cgh.citl import straight_through_loss
from benchctl.files import atomic_write_bytes
from benchctl.optics import crop_roi, lsq_scale, psnr
from benchctl.profiles import LaserChannel
from benchctl.runner.api import (
    BenchctlError,
    Context,
    DarkFrames,
    Expose,
    ExposureCap,
    ExposureMode,
    ExposureParameters,
    Frames,
    HologramParameters,
    PeakGoal,
    RegistrationMode,
    Step,
    StepRedo,
    channels,
    compute_hologram,
    exposure_cap_w,
    load_image,
    measure,
    power_w,
    prepared_target,
    probe_step,
    probed_power,
    registered,
    save_hologram,
    save_image,
    shown,
    state_path,
    target_plane,
    unknown_caps,
    unknown_setpoints,
)
from benchctl.runner.builtin import registration
from benchctl.runner.builtin.citl.report import citl_report, merged_scores
from benchctl.targets import active_channels

DESCRIPTION = "camera in the loop: per colour, display, capture, register and step the phase on the captured error"


class CitlParameters(ExposureParameters, kw_only=True):
    """What to optimise on the bench, how long, how fast, and what to keep on disk."""

    target: str = "chart:bars"
    frames: Frames = 1  # RAW frames averaged per iteration
    dark_frames: DarkFrames = 0  # per iteration (the decoder removes the black level)
    iterations: Annotated[int, Meta(ge=1, le=10_000)] = 50  # Adam steps on the captured error
    # Adam moves each phase value by about this (radians) per step: above 1 a step scrambles the hologram
    learning_rate: Annotated[float, Meta(gt=0, le=1)] = 0.05
    # "cosine": the learning rate falls from learning_rate to 0 over the iterations (late steps, whose gradient is
    # mostly camera noise, stay small); "constant"
    schedule: Literal["cosine", "constant"] = "cosine"
    start: Literal["dpac", "sgd"] = "dpac"  # the model hologram to start from
    start_iterations: Annotated[int, Meta(ge=1)] = 100  # model-only SGD steps of an SGD start
    # disk policy: RAW frames kept for the first and last iteration and every Nth (0: first and last only)
    keep_raw_every: Annotated[int, Meta(ge=0)] = 10
    baseline: bool = True  # capture model-only SGD at the same budget too
    registration: RegistrationMode = "auto"
    exposure: ExposureMode = "auto"  # "auto": a probe frame of the start hologram sets the power for every capture
    peak_goal: PeakGoal = 0.7  # fraction of full scale
    max_exposure_power: ExposureCap = None  # the most "auto" may set: "5mW", "10%" or per colour; default max_power_mw
    device: Literal["auto", "cpu", "cuda"] = "auto"  # where the gradient runs; "auto": a CUDA GPU if there is one


PARAMETERS = CitlParameters
DIVERGENCE = 4.0  # a captured loss above this many times iteration 0's: the phase diverged
MIN_SCALE = 1 / 64  # the learning rate is halved on divergence at most down to this fraction

TIMING_KEYS = ("display_s", "exposure_s", "transfer_s", "decode_s", "register_s", "gradient_s", "laser_s",
               "save_s", "render_s", "total_s")
"""Seconds per iteration: display_s (SLM frame shown, settle included), exposure_s (shutter release to image
ready, all frames, the simulator's rendering excluded), transfer_s (image download, where the driver reports it),
decode_s, register_s, gradient_s (model forward, backward, Adam step), laser_s (setpoint, emission on/off and
read-backs), save_s (images, state), render_s (the simulated camera's rendering: 0 on a real camera), total_s."""


def plan(context: Context) -> list[Step]:
    """Registration if needed; per colour: the start hologram, iterations + 1 captures, the baseline; the report."""
    params = context.parameters(CitlParameters)
    gradient_device(params.device)
    unknown_setpoints(context)
    unknown_caps(context, params.max_exposure_power)
    target = prepared_target(context.profile, params.target, "parameters.target")
    present = active_channels(target)
    used = [c for c in channels(context) if present[target_plane(c)]]
    if not used:
        raise BenchctlError(f"parameters.target: {params.target!r} has none of the colours "
                            f"{[c.name for c in channels(context)]}")
    steps = registration.registration_first(context, used, params, params.registration)
    count = params.iterations
    for channel in used:
        name = channel.name
        steps.append(Step(f"citl/{name}/start", f"start hologram {name} ({params.start})",
                          _starter(target, channel)))
        cap = exposure_cap_w(context, channel, params.max_exposure_power)
        if params.exposure == "auto":
            steps.append(probe_step(context, f"citl/{name}/probe", channel, shown(f"citl/{name}/start"),
                                    "probe exposure of the start hologram", params.peak_goal, cap))
        power = None if params.exposure == "auto" else power_w(context, channel)
        for k in range(count + 1):
            what = "capture the final phase" if k == count else "capture, register, step the phase"
            steps.append(Step(f"citl/{name}/{k:04d}", f"CITL {name} iteration {k}/{count}: {what}",
                              _iteration(target, channel, k),
                              (Expose(name, power, params.frames, params.dark_frames,
                                      keeps_raw(k, count, params.keep_raw_every), max_w=cap),)))
        if params.baseline:
            steps.append(Step(f"citl/{name}/baseline", f"model-only SGD {name} at {_budget(params)} iterations, "
                              "captured", _baseline(target, channel),
                              (Expose(name, power, params.frames, params.dark_frames, max_w=cap),)))
    steps.append(Step("report", "metrics.json, metrics.csv and report.html", _reporter(target, used)))
    return steps


def _budget(params: CitlParameters) -> int:
    """Adam steps CITL's final phase has had: the SGD start's (if any) plus its own."""
    return params.iterations + (params.start_iterations if params.start == "sgd" else 0)


def gradient_device(choice: str) -> torch.device:
    """The device of parameters.device ("auto": CUDA when torch sees a GPU, else the CPU)."""
    if choice == "auto":
        choice = "cuda" if torch.cuda.is_available() else "cpu"
    elif choice == "cuda" and not torch.cuda.is_available():
        raise BenchctlError(f"parameters.device: 'cuda', but torch {torch.__version__} sees no CUDA GPU "
                            "(use 'auto' or 'cpu')")
    return torch.device(choice)


def _synchronised(device: torch.device) -> None:
    """Wait for `device`'s queued work, so a clock read afterwards times it (CUDA runs asynchronously)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def learning_rate(params: CitlParameters, k: int) -> float:
    """The learning rate of iteration k's Adam step (k = 0 .. iterations - 1)."""
    if params.schedule == "constant":
        return params.learning_rate
    return params.learning_rate * 0.5 * (1 + math.cos(math.pi * k / params.iterations))


def keeps_raw(k: int, iterations: int, every: int) -> bool:
    """Whether iteration k keeps its RAW frames: the first, the last, and every `every`-th (0: none between)."""
    return k in (0, iterations) or (every > 0 and k % every == 0)


def _target_roi(context: Context, target: torch.Tensor, channel: LaserChannel) -> torch.Tensor:
    assert context.profile.optics is not None
    return crop_roi(target[target_plane(channel)], context.profile.optics.roi)


# -- the optimiser state ----------------------------------------------------------------------------------------

def _state_file(context: Context, channel: LaserChannel, k: int) -> Path:
    return state_path(context, channel.name, f"{k:04d}.npz")


class StateDamaged(ValueError):
    """A state file that cannot be used as saved: missing, changed since saved, unreadable or inconsistent."""


def _save_state(path: Path, phase: torch.Tensor, optimiser: torch.optim.Adam | None, lr_scale: float = 1.0) -> str:
    """The phase, Adam's moments and step count, exactly (float32), and the learning rate's scale, written atomically;
    returns the file's SHA-256, which the step's result keeps."""
    arrays: dict[str, np.ndarray] = {"phase": phase.detach().cpu().numpy(), "step": np.zeros((), np.float32),
                                     "lr_scale": np.array(lr_scale, np.float64)}
    state = optimiser.state.get(optimiser.param_groups[0]["params"][0]) if optimiser else None
    if state:
        arrays.update({key: state[key].cpu().numpy() for key in ("step", "exp_avg", "exp_avg_sq")})
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]  # numpy's stub: a key could be its bool allow_pickle
    atomic_write_bytes(path, buffer.getvalue())
    return hashlib.sha256(buffer.getvalue()).hexdigest()


def _read_state(path: Path, sha256: str | None) -> dict[str, np.ndarray]:
    """The arrays of a state file, checked against the SHA-256 recorded when it was saved (if given), read without
    pickles, their shapes consistent; StateDamaged says what is wrong."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise StateDamaged(f"{path.name}: {exc.strerror or exc}") from None
    if sha256 is not None and (actual := hashlib.sha256(data).hexdigest()) != sha256:
        raise StateDamaged(f"{path.name} changed since it was saved (SHA-256 {actual[:12]}..., saved {sha256[:12]}...)")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise StateDamaged(f"{path.name} cannot be read as a saved state: {exc}") from None
    phase = arrays.get("phase")
    moments = [arrays.get(name) for name in ("exp_avg", "exp_avg_sq")] if float(arrays.get("step", 0)) > 0 else []
    if (phase is None or phase.ndim != 2 or phase.dtype != np.float32
            or any(m is None or m.shape != phase.shape for m in moments) or not np.isfinite(phase).all()):
        raise StateDamaged(f"{path.name} does not hold a finite float32 phase (with Adam's moments of its shape)")
    return arrays


def _load_state(path: Path, learning_rate: float, device: torch.device | str = "cpu",
                sha256: str | None = None) -> tuple[torch.Tensor, torch.optim.Adam, float]:
    """The phase (a leaf to optimise, on `device`), its Adam optimiser and the learning rate's scale as `_save_state`
    left them (StateDamaged if the file is not as saved)."""
    data = _read_state(path, sha256)
    phase = torch.from_numpy(data["phase"].copy()).to(device).requires_grad_()
    optimiser = torch.optim.Adam([phase], lr=learning_rate)
    if float(data["step"]) > 0:  # Adam keeps its step count on the CPU, its moments beside the parameter
        optimiser.state[phase] = {"step": torch.from_numpy(data["step"].copy()),
                                  "exp_avg": torch.from_numpy(data["exp_avg"].copy()).to(device),
                                  "exp_avg_sq": torch.from_numpy(data["exp_avg_sq"].copy()).to(device)}
    return phase, optimiser, float(data.get("lr_scale", 1.0))


def _writer(channel: LaserChannel, k: int) -> str:
    """The step that saves iteration k's state: the start for k = 0, else iteration k - 1."""
    return f"citl/{channel.name}/start" if k == 0 else f"citl/{channel.name}/{k - 1:04d}"


def _diverged(channel: LaserChannel, k: int, what: str, rate: float, scale: float, redo: str) -> BenchctlError:
    """The error that stops a diverged run; a resume goes back to `redo` at half the learning rate's `scale`."""
    halved = f" x {scale:g} after earlier divergences" if scale != 1 else ""
    where = f"CITL {channel.name} diverged at iteration {k}: {what} (learning_rate {rate:g}{halved})"
    if scale / 2 < MIN_SCALE:
        return BenchctlError(f"{where}, already halved down to {MIN_SCALE:g}: start a new run with a lower "
                             "learning_rate")
    back = "this iteration's start" if redo.endswith(f"{k:04d}") else f"iteration {k - 1}'s phase"
    return StepRedo(f"{where}: the run stops; a resume continues from {back} at half that rate, or start a new run "
                    "with a lower learning_rate", redo, stop=True, diverged=True)


# -- one capture, decoded and registered --------------------------------------------------------------------------

def _capture(context: Context, channel: LaserChannel, gray: np.ndarray,
             keep: bool) -> tuple[np.ndarray, dict[str, Any], dict[str, float]]:
    """Display `gray`, expose it (RAW files kept with `keep`, else only in memory), decode and register the
    colour's plane: (ROI linear signal, JSON-ready record, seconds per stage)."""
    params = context.parameters(CitlParameters)
    power = (probed_power(f"citl/{channel.name}/probe")(context) if params.exposure == "auto"
             else power_w(context, channel))
    measured = measure(context, channel, power, gray, frames=params.frames, dark_frames=params.dark_frames,
                       keep=keep, read_later=False)
    clock = time.perf_counter
    start = clock()
    image = measured.image
    decoded = clock()
    plane = registered(context, image, channel)
    registered_at = clock()
    exposure = measured.exposure
    metadata = [frame.metadata for frame in (*exposure.frames, *exposure.darks)]
    render = sum(float(m.get("render_s", 0.0)) for m in metadata)
    transfer = sum(float(m.get("transfer_s", 0.0)) for m in metadata)
    timing = {"display_s": exposure.timing["display_s"], "laser_s": exposure.timing["laser_s"],
              "exposure_s": exposure.timing["capture_s"] - render - transfer, "transfer_s": transfer,
              "render_s": render, "decode_s": decoded - start, "register_s": registered_at - decoded}
    record = {key: value for key, value in measured.record.items()
              if key in ("setpoint_w", "slm_frame", "folder", "archived")}
    record["saturated_fraction"] = round(float(image.saturation_fraction), 6)
    return plane, record, timing


def _amplitude_error(plane: np.ndarray, target_roi: torch.Tensor) -> tuple[torch.Tensor, float, float]:
    """The captured amplitude (sqrt of the signal, negatives clipped), its MSE and PSNR against the target after
    least-squares scaling."""
    captured = torch.from_numpy(np.sqrt(np.clip(plane, 0.0, None)))
    scaled = lsq_scale(captured, target_roi) * captured
    loss = torch.nn.functional.mse_loss(scaled, target_roi)
    return captured, float(loss), float(psnr(scaled, target_roi, data_range=1.0))


def _save_plane(context: Context, channel: LaserChannel, name: str, plane: np.ndarray) -> dict[str, Any]:
    """The registered plane as a 16-bit PNG on the ROI, scaled by its maximum (recorded to undo the scaling)."""
    peak = float(max(plane.max(), 1e-12))
    file = save_image(context, np.clip(plane, 0, None) / peak, "citl", channel.name, f"{name}.png")
    return {"file": file, "full_scale": peak}


# -- the steps ------------------------------------------------------------------------------------------------------

def _starter(target: torch.Tensor, channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        params = context.parameters(CitlParameters)
        iterations = params.start_iterations if params.start == "sgd" else None
        result = compute_hologram(context, target, channel,
                                  HologramParameters(method=params.start, iterations=iterations))
        file = save_hologram(context, result.gray, "citl", channel.name, "start.png")
        phase = torch.from_numpy(context.decode(result.gray, channel.name))
        digest = _save_state(_state_file(context, channel, 0), phase, None)
        return {"file": file, "method": params.start, "iterations": iterations, "state_sha256": digest,
                "seconds": round(result.seconds, 4), "simulated": {k: round(v, 4) for k, v in result.scores.items()}}

    return action


def _iteration(target: torch.Tensor, channel: LaserChannel, k: int):
    def action(context: Context) -> dict[str, Any]:
        params, clock = context.parameters(CitlParameters), time.perf_counter
        begin = clock()
        count, device = params.iterations, gradient_device(params.device)
        key, writer = f"citl/{channel.name}/{k:04d}", _writer(channel, k)
        try:
            phase, optimiser, scale = _load_state(_state_file(context, channel, k), params.learning_rate, device,
                                                  context.result(writer).get("state_sha256"))
        except StateDamaged as exc:
            raise StepRedo(f"CITL {channel.name} iteration {k}: its state {exc}", writer) from None
        scale *= 0.5 ** context.divergences(key)
        gray = context.encode(phase.detach(), channel.name)
        keep = keeps_raw(k, count, params.keep_raw_every)
        plane, record, timing = _capture(context, channel, gray, keep)
        target_roi = _target_roi(context, target, channel)
        start = clock()
        captured, loss, score = _amplitude_error(plane, target_roi)
        if k > 0:
            first = context.result(f"citl/{channel.name}/0000")["loss"]
            if not math.isfinite(loss) or loss > DIVERGENCE * first:
                raise _diverged(channel, k, f"captured loss {loss:.3g}, {loss / first:.1f} x iteration 0's "
                                f"{first:.3g}", params.learning_rate, scale, writer)
        rate = learning_rate(params, k) * scale if k < count else 0.0
        if k < count:
            with torch.enable_grad():
                optimiser.param_groups[0]["lr"] = rate
                optimiser.zero_grad(set_to_none=True)
                setup = context.setup(channel.name, as_displayed=True)
                straight_through_loss(phase, captured.to(device), target_roi.to(device), setup).backward()
                optimiser.step()
                with torch.no_grad():
                    phase.copy_(setup.within_reach(phase))
            _synchronised(device)
            if not bool(torch.isfinite(phase).all()):
                raise _diverged(channel, k, "the phase is no longer finite after its step",
                                params.learning_rate, scale, key)
        timing["gradient_s"] = clock() - start
        start = clock()
        record.update(_save_plane(context, channel, f"{k:04d}", plane))
        if keep:
            record["hologram"] = save_hologram(context, gray, "citl", channel.name, f"{k:04d}.png", read_later=False)
        if k < count:
            record["state_sha256"] = _save_state(_state_file(context, channel, k + 1), phase, optimiser, scale)
        if k > 0:
            _state_file(context, channel, k - 1).unlink(missing_ok=True)  # iteration k - 1 finished: not needed
        timing["save_s"] = clock() - start
        timing["total_s"] = clock() - begin
        context.say(f"      {channel.name} {k}/{count}: captured PSNR {score:.2f} dB amplitude, loss {loss:.3e}")
        return {"iteration": k, "loss": loss, "psnr_amplitude_db": round(score, 4), **record, "device": str(device),
                "learning_rate": rate, "timing": {name: round(timing[name], 6) for name in TIMING_KEYS}}

    return action


def _baseline(target: torch.Tensor, channel: LaserChannel):
    def action(context: Context) -> dict[str, Any]:
        budget = _budget(context.parameters(CitlParameters))
        result = compute_hologram(context, target, channel, HologramParameters(method="sgd", iterations=budget))
        plane, record, _ = _capture(context, channel, result.gray, keep=True)
        _, loss, score = _amplitude_error(plane, _target_roi(context, target, channel))
        frame = save_hologram(context, result.gray, "citl", channel.name, "baseline.png")
        context.say(f"      {channel.name}: model-only SGD ({budget} iterations) captured PSNR {score:.2f} dB")
        return {"iterations": budget, "loss": loss, "psnr_amplitude_db": round(score, 4), **record,
                **_save_plane(context, channel, "baseline", plane), "hologram": frame,
                "simulated": {k: round(v, 4) for k, v in result.scores.items()}}

    return action


def _reporter(target: torch.Tensor, used: list[LaserChannel]):
    def action(context: Context) -> dict[str, Any]:
        assert context.profile.optics is not None
        params = context.parameters(CitlParameters)
        count = params.iterations
        target_roi = crop_roi(target, context.profile.optics.roi)
        iterations = {c.name: [context.result(f"citl/{c.name}/{k:04d}") for k in range(count + 1)] for c in used}
        baseline = {c.name: context.result(f"citl/{c.name}/baseline") for c in used} if params.baseline else {}

        def planes(results: dict[str, dict[str, Any]]) -> dict[int, np.ndarray]:
            return {target_plane(c): load_image(context, results[c.name]["file"]) / 65535.0
                    * results[c.name]["full_scale"] for c in used}

        def merged(results: dict[str, dict[str, Any]], image: str | None = None) -> dict[str, Any]:
            """The merged capture's scores (with SSIM, warnings and the image where `image` names it)."""
            return merged_scores(context, planes(results), target_roi, image)

        per_k = [merged({name: rows[k] for name, rows in iterations.items()},
                        "merged-first.png" if k == 0 else "merged-last.png" if k == count else None)
                 for k in range(count + 1)]
        return citl_report(context, {
            "target": params.target, "iterations": iterations, "merged": per_k,
            "baseline": {"colours": baseline, "merged": merged(baseline, "merged-baseline.png"),
                         "iterations": _budget(params)} if baseline else None,
            "start": {c.name: context.result(f"citl/{c.name}/start") for c in used},
            "timing_keys": list(TIMING_KEYS), "disk": _disk(context, iterations, used),
            "target_image": save_image(context, target_roi.square(), "citl", "target.png", srgb=True)})

    return action


def _disk(context: Context, iterations: dict[str, list[dict[str, Any]]], used: list[LaserChannel]) -> dict[str, Any]:
    """Bytes the run keeps per iteration: registered planes (every iteration), RAW and displayed frames (the kept
    iterations), and the optimiser state (two iterations' worth at a time, one left at the end)."""
    def size(relative: str) -> int:
        path = context.path(relative)
        return path.stat().st_size if path.is_file() else 0

    rows = [row for rows in iterations.values() for row in rows]
    kept = [row for row in rows if "folder" in row]
    raw = sum(size(name) for row in kept for name in row["archived"])
    frames = sum(size(row["hologram"]) for row in kept)
    planes = sum(size(row["file"]) for row in rows)
    states = [p.stat().st_size for c in used for p in state_path(context, c.name).glob("*.npz")]
    return {"iterations": len(rows), "kept_raw_iterations": len(kept),
            "registered_bytes_per_iteration": round(planes / len(rows)),
            "raw_bytes_per_kept_iteration": round(raw / len(kept)) if kept else 0,
            "hologram_bytes_per_kept_iteration": round(frames / len(kept)) if kept else 0,
            "state_bytes": max(states, default=0), "citl_bytes": raw + frames + planes + sum(states)}
