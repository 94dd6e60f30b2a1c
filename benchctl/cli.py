"""The `benchctl` command line: parses arguments and calls one function per command; no logic lives here."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import benchctl
from benchctl.errors import BenchctlError

EPILOG = """targets: a bundled chart or photo (see `benchctl targets`) such as chart:siemens or photo:coffee, or an
image file.
profiles: a path to a TOML file or a name in hardware_profiles/ (default: simulated, or $BENCHCTL_PROFILE)."""


def _size(text: str) -> tuple[int, int]:
    try:
        rows, cols = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 1088x1920 (rows x cols), got {text!r}") from None
    if rows < 1 or cols < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return rows, cols


def _int_list(text: str) -> tuple[int, ...]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers like 10,50,200, got {text!r}") from None
    if any(v < 1 for v in values):
        raise argparse.ArgumentTypeError(f"iteration counts must be >= 1, got {text!r}")
    return values


def _names(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


class _VersionAction(argparse.Action):
    """--version, reading the installed metadata only when asked (building the parser must stay cheap)."""

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
        parser.exit(message=f"benchctl {benchctl.__version__}\n")


def _add_profile(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--profile", "-p", metavar="P",
                        help="hardware profile: TOML path or name in hardware_profiles/ (default: simulated)")


def _cmd_generate(args: argparse.Namespace) -> int:
    from benchctl.console import Progress
    from benchctl.profiles import load_profile
    from benchctl.runner.generate import run_generate

    profile = load_profile(args.profile)
    metrics = run_generate(args.target, profile, Path(args.out), method=args.method, iterations=args.iterations,
                           colours=args.colours, seed=args.seed, progress=Progress, checkpoint=args.checkpoint)
    if metrics["checkpoint"]:
        print(f"{args.method}: trained models from {metrics['checkpoint']}")
    if metrics["optical_model"]:
        print(f"fitted optical model: {metrics['optical_model']}")
    for name, colour in metrics["colours"].items():
        if colour["skipped"]:
            print(f"{name:>6}: skipped (black in the target)")
        else:
            print(f"{name:>6}: {colour['seconds']:.2f} s, PSNR {colour['psnr_amplitude_db']:.2f} dB amplitude, "
                  f"SSIM {colour['ssim_amplitude']:.3f}")
    merged = metrics["merged"]
    print(f"merged: PSNR {merged['psnr_srgb_db']:.2f} dB sRGB, SSIM {merged['ssim_srgb']:.3f}; wrote {args.out}/")
    return 0


def _cmd_bench_speed(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.speed_vs_error import (
        DEFAULT_BUDGETS,
        DEFAULT_TARGETS,
        FULL_BUDGETS,
        resized_profile,
        run_speed_vs_error,
    )
    from benchctl.console import Progress
    from benchctl.errors import BadValueError
    from benchctl.profiles import load_profile

    profile = load_profile(args.profile).require("slm", "optics", "laser")
    if args.full and args.size:
        raise BadValueError("--full runs at the profile's own grid; leave out --size")
    size = profile.slm.shape if args.full else args.size or (profile.slm.height // 4, profile.slm.width // 4)
    run_speed_vs_error(resized_profile(profile, size), targets=tuple(args.targets or DEFAULT_TARGETS),
                       methods=tuple(args.methods) if args.methods else None,
                       budgets=args.iterations or (FULL_BUDGETS if args.full else DEFAULT_BUDGETS),
                       colours=args.colours, seed=args.seed, out_dir=Path(args.out), progress=Progress)
    return 0


def _cmd_bench_propagation(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.propagation import PAPER_SIZES, run_propagation_bench
    from benchctl.files import ensure_dir, write_csv
    from benchctl.profiles import load_profile

    profile = load_profile(args.profile)
    (h, w), (rh, rw) = profile.slm.shape, profile.optics.roi
    rows = run_propagation_bench(sizes=args.size or PAPER_SIZES,
                                 wavelengths=[(c.name, c.wavelength_m) for c in profile.channels],
                                 distance_m=profile.optics.distance_m, pitch_m=profile.slm.pitch_m,
                                 roi_fraction=(rh / h, rw / w), repeats=args.repeats)
    if args.out:
        print(f"wrote {write_csv(ensure_dir(Path(args.out)) / 'propagation.csv', rows)}")
    return 0


def _cmd_profile_check(args: argparse.Namespace) -> int:
    from benchctl.profiles import load_profile
    from benchctl.runner.holograms import describe_propagation

    profile = load_profile(args.path)
    print(profile.describe())
    print(describe_propagation(profile))
    print(f"{profile.path}: OK")
    return 0


def _print_lines(lines: list[str]) -> int:
    for line in lines:
        print(line)
    return 0


def _cmd_device(args: argparse.Namespace) -> int:
    """laser / slm / sim subcommands: each maps to one function of benchctl.runner.device_commands."""
    from benchctl.profiles import load_profile
    from benchctl.runner import device_commands as dc

    if args.command == "devices":
        return _print_lines(dc.devices_found())
    if args.command == "sim":
        if args.sim_command == "status":
            return _print_lines(dc.sim_status())
        if args.sim_command == "reset":
            return _print_lines(dc.sim_reset())
        return _print_lines(dc.sim_fault(args.device, args.faults, args.clear, load_profile(args.profile)))
    profile = load_profile(args.profile)
    if args.command == "camera":
        if args.camera_command == "info":
            return _print_lines(dc.camera_info(profile))
        return _print_lines(dc.camera_capture(profile, Path(args.output), args.frames))
    action = args.laser_command if args.command == "laser" else args.slm_command
    if args.command == "laser":
        if action == "status":
            return _print_lines(dc.laser_status(profile))
        if action == "set":
            return _print_lines(dc.laser_set(profile, args.channel, args.power))
        if action == "on":
            duration = dc.parse_duration(args.duration) if args.duration else None
            return _print_lines(dc.laser_on(profile, args.channel, duration, args.leave_on))
        return _print_lines(dc.laser_off(profile, args.channel))
    if action == "info":
        return _print_lines(dc.slm_info(profile))
    if action == "show":
        return _print_lines(dc.slm_show(profile, Path(args.file), args.channel))
    return _print_lines(dc.slm_blank(profile))


def _add_device_commands(sub: argparse._SubParsersAction) -> None:
    laser = sub.add_parser("laser", help="laser: status, setpoints, emission",
                           description="Connecting to the laser turns emission off on every channel (safety); "
                                       "emission is off again when a command exits unless --leave-on says "
                                       "otherwise.").add_subparsers(dest="laser_command", metavar="ACTION",
                                                                    required=True)
    status = laser.add_parser("status", help="per channel: wavelength, setpoint, measured power, emission, "
                                             "interlock, faults (changes nothing)")
    setp = laser.add_parser("set", help="change a channel's power setpoint (emission stays off)")
    setp.add_argument("channel", help="channel name from the profile, e.g. red")
    setp.add_argument("power", help="power: 20mW, 0.02W or 5%% (of the channel's max_power_mw)")
    on = laser.add_parser("on", help="emission on for a time or until Ctrl-C, then off")
    on.add_argument("channel", help="channel name from the profile, e.g. red")
    on.add_argument("--for", dest="duration", metavar="TIME", help="how long, e.g. 30s, 500ms, 2m "
                                                                   "(default: until Ctrl-C)")
    on.add_argument("--leave-on", action="store_true", help="leave emission on after the command exits")
    off = laser.add_parser("off", help="emission off on one channel or all")
    off.add_argument("channel", nargs="?", default="all", help="channel name or 'all' (default: all)")
    for parser in (status, setp, on, off):
        _add_profile(parser)
        parser.set_defaults(func=_cmd_device)

    slm = sub.add_parser("slm", help="SLM: info, show an image or phase, blank").add_subparsers(
        dest="slm_command", metavar="ACTION", required=True)
    info = slm.add_parser("info", help="driver, resolution, pitch, bit depth, settle time, lookup tables")
    show = slm.add_parser("show", help="show an 8-bit image as is, or a .npy phase (radians) encoded for a channel")
    show.add_argument("file", help="PNG/TIFF gray image of the SLM's size, or .npy phase in radians")
    show.add_argument("--channel", "-c", help="laser channel whose lookup table encodes a .npy phase")
    blank = slm.add_parser("blank", help="show gray level 0 everywhere")
    for parser in (info, show, blank):
        _add_profile(parser)
        parser.set_defaults(func=_cmd_device)

    camera = sub.add_parser("camera", help="camera: info, capture RAW frames").add_subparsers(
        dest="camera_command", metavar="ACTION", required=True)
    cinfo = camera.add_parser("info", help="what the camera says it is, and the capture settings")
    capture = camera.add_parser("capture", help="capture RAW frames exactly as the camera delivers them")
    capture.add_argument("--output", "-o", required=True, metavar="FILE",
                         help="RAW file to write (several frames: FILE-000.dng, FILE-001.dng, ...)")
    capture.add_argument("--frames", "-n", type=_positive_int, help="frames to capture (default: the profile's)")
    for parser in (cinfo, capture):
        _add_profile(parser)
        parser.set_defaults(func=_cmd_device)
    devices = sub.add_parser("devices", help="serial ports, PTP cameras and framebuffers on this machine")
    devices.set_defaults(func=_cmd_device)

    sim = sub.add_parser("sim", help="the simulated bench's remembered state").add_subparsers(
        dest="sim_command", metavar="ACTION", required=True)
    sim.add_parser("status", help="where the state is kept and what each simulated device holds")
    sim.add_parser("reset", help="forget all simulated device state (like a power cycle)")
    fault = sim.add_parser("fault", help="make a simulated device misbehave from its next connection on")
    fault.add_argument("device", help="simulated device name, e.g. rgb-laser (from sim://rgb-laser), or sim-camera")
    fault.add_argument("faults", nargs="*", help="lasers: no_reply, garbled, echo, slow, interlock_open, device_fault, "
                                                 "clamp, drop_after=N; sim-camera: unplug_at=N (cable pulled before "
                                                 "frame N)")
    fault.add_argument("--clear", action="store_true", help="remove every fault")
    _add_profile(fault)  # whose sim:// lasers are known devices
    for parser in sim.choices.values():
        parser.set_defaults(func=_cmd_device)


def _cmd_models(args: argparse.Namespace) -> int:
    from benchctl.profiles import load_profile
    from benchctl.runner.holograms import list_methods

    profile = load_profile(args.profile)
    shape = args.size or profile.require("slm").slm.shape
    print(f"hologram methods at {shape[0]}x{shape[1]} (checkpoints for profile {profile.name!r}):")
    return _print_lines(list_methods(shape, profile))


def _cmd_train(args: argparse.Namespace) -> int:
    from benchctl.cgh.learned.training import TrainSettings
    from benchctl.profiles import load_profile
    from benchctl.runner.training import run_train

    settings = TrainSettings(method=args.method, data=args.data, size=args.size,
                             colours=tuple(args.colours) if args.colours else None, epochs=args.epochs, lr=args.lr,
                             loss=args.loss, vgg_weights=args.vgg_weights, batch_size=args.batch_size, seed=args.seed,
                             val_fraction=args.val_fraction, max_steps=args.max_steps,
                             weights_dtype=args.weights_dtype, model_calibration=args.model_calibration)
    run_train(load_profile(args.profile), settings, args.out, resume=args.resume)
    return 0


def _cmd_bench_learned(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.learned import run_learned_bench
    from benchctl.profiles import load_profile

    run_learned_bench(load_profile(args.profile), size=args.size, methods=args.methods, checkpoints=args.checkpoint,
                      repeats=args.repeats, training_memory=not args.inference_only, out_dir=args.out)
    return 0


def _cmd_bench_reproduce(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.reproduce import DEFAULT_METHODS, reproduce_command, run_reproduction
    from benchctl.profiles import load_profile

    methods = args.methods or list(DEFAULT_METHODS)
    command = reproduce_command(args.profile, args.size, args.minutes, args.steps, methods, args.colour, args.data,
                                args.evaluations, args.lr, args.seed, args.threads, args.out)
    run_reproduction(load_profile(args.profile), size=args.size, cpu_seconds=None if args.minutes is None
                     else args.minutes * 60, steps=args.steps, methods=methods, colour=args.colour, data=args.data,
                     evaluations=args.evaluations, lr=args.lr, seed=args.seed, memory=not args.no_memory,
                     threads=args.threads, out_dir=args.out, command=command)
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    from benchctl.runner.engine import run_procedure

    if args.procedure is None and args.resume is None:
        raise BenchctlError("give a procedure file (e.g. procedures/colour_capture.toml) or --resume RUN_DIR")
    if args.procedure is not None and args.resume is not None:
        raise BenchctlError("give either a procedure file or --resume RUN_DIR, not both (a resumed run uses its own "
                            "copy of the procedure)")
    run_procedure(args.procedure, profile=args.profile, out=args.out, dry_run=args.dry_run, resume=args.resume)
    return 0


def _cmd_targets(args: argparse.Namespace) -> int:
    from benchctl.targets import list_targets

    for name, description in list_targets().items():
        print(f"{name:<16} {description}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser (also used by the docs and tests).

    Building it imports nothing heavy (no torch, no networks): `benchctl laser off` must start instantly.
    Method names are therefore checked when a command runs, not by argparse `choices`.
    """
    parser = argparse.ArgumentParser(
        prog="benchctl",
        description="Holographic-display experiments on an optical bench, real or simulated.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action=_VersionAction, nargs=0, help="show the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    gen = sub.add_parser("generate", help="phase holograms for a target, with simulated reconstruction and scores",
                         description="Generate one 8-bit phase PNG per colour (as the SLM displays it), the "
                                     "simulated reconstruction and metrics.json. Colours that are black in the "
                                     "target are skipped.", epilog=EPILOG,
                         formatter_class=argparse.RawDescriptionHelpFormatter)
    gen.add_argument("target", help="chart or photo name (e.g. chart:siemens, photo:coffee) or image file")
    gen.add_argument("--method", "-m", default="dpac",
                     help="hologram method (default: dpac; `benchctl models` lists them all); learned ones, alone "
                          "or refined as <learned>+sgd, need a trained checkpoint")
    gen.add_argument("--checkpoint", type=Path, metavar="CKPT",
                     help="trained models for a learned method (default: the one shipped for the profile)")
    gen.add_argument("--iterations", "-n", type=_positive_int, help="iterations for iterative methods "
                                                                   "(default: the method's own)")
    gen.add_argument("--colours", "--colors", type=_names, metavar="LIST",
                     help="comma-separated laser channels, e.g. red,green (default: all in the profile)")
    gen.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    gen.add_argument("--out", "-o", required=True, metavar="OUTDIR", help="folder for the PNGs and metrics.json")
    _add_profile(gen)
    gen.set_defaults(func=_cmd_generate)

    bench = sub.add_parser("bench", help="benchmarks: speed against error").add_subparsers(
        dest="bench", metavar="BENCH", required=True)
    speed = bench.add_parser("speed-vs-error", help="seconds per frame against PSNR/SSIM for each method and budget",
                             description="Runs every hologram method at several iteration budgets on the targets, "
                                         "prints a table and writes speed_vs_error.csv (+ .png with matplotlib).")
    speed.add_argument("--targets", nargs="+", metavar="TARGET", help="targets (default: chart:siemens chart:bars "
                                                                     "chart:text and the held-out photographs)")
    speed.add_argument("--methods", type=_names, metavar="LIST",
                       help="comma-separated methods (default: all classical ones, and learned ones whose "
                            "shipped checkpoint fits the benchmark's grid, alone and refined: <name>+sgd)")
    speed.add_argument("--iterations", type=_int_list, metavar="LIST",
                       help="iteration budgets for iterative methods (default: 10,50,200,500; 10,50 with --full)")
    speed.add_argument("--size", type=_size, metavar="HxW",
                       help="SLM grid for the benchmark; ROI and distance scaled to keep the Fresnel number "
                            "(default: a quarter of the profile's grid per axis)")
    speed.add_argument("--full", action="store_true",
                       help="the profile's own geometry (the paper's 1088x1920 on the simulated profile): slow")
    speed.add_argument("--colours", type=_names, metavar="LIST",
                       help="comma-separated laser channels, e.g. green (default: all in the profile)")
    speed.add_argument("--seed", type=int, default=0)
    speed.add_argument("--out", "-o", default="bench-out", metavar="DIR", help="output folder (default: bench-out)")
    _add_profile(speed)
    speed.set_defaults(func=_cmd_bench_speed)

    prop = bench.add_parser("propagation", help="padding modes: time vs bare FFT and error vs a float64 reference",
                            description="For each padding mode, colour and grid: the plan, the time of one "
                                        "propagation, its ratio to a bare fft2+ifft2 of the same padded grid and "
                                        "the relative L2 error on the ROI against a converged float64 propagation.")
    prop.add_argument("--size", type=_size, nargs="+", metavar="HxW",
                      help="grids to measure (default: 1088x1920 2160x3840)")
    prop.add_argument("--repeats", type=_positive_int, default=5, help="timed repeats per case (default: 5)")
    prop.add_argument("--out", "-o", metavar="DIR", help="also write propagation.csv here")
    _add_profile(prop)
    prop.set_defaults(func=_cmd_bench_propagation)

    learned = bench.add_parser("learned", help="learned methods side by side: parameters, inference time, training "
                                               "memory, PSNR/SSIM, ratios to the baseline network",
                               description="Per learned method, measured in one run: trainable parameters, inference "
                                           "seconds per frame, peak memory of one training step (a fresh subprocess "
                                           "per model on CPU; the allocator's peak on CUDA), PSNR/SSIM where a "
                                           "checkpoint fits, and ratios against holonet / ccnn. Writes learned.csv.")
    learned.add_argument("--size", type=_size, metavar="HxW",
                         help="grid (default: the profile's); pitch and distance kept, ROI scaled, as for training")
    learned.add_argument("--methods", type=_names, metavar="LIST",
                         help="comma-separated learned methods (default: all; the family baselines are added)")
    learned.add_argument("--checkpoint", type=Path, nargs="+", default=[], metavar="CKPT",
                         help="trained checkpoints to score (default: the shipped ones that fit the grid)")
    learned.add_argument("--repeats", type=_positive_int, default=3, help="timed inference runs (default: 3)")
    learned.add_argument("--inference-only", action="store_true", help="skip the training-step memory subprocesses")
    learned.add_argument("--out", "-o", default="bench-out", type=Path, metavar="DIR",
                         help="output folder (default: bench-out)")
    _add_profile(learned)
    learned.set_defaults(func=_cmd_bench_learned)

    reproduce = bench.add_parser("reproduce", help="the paper's quality tables at a CPU-trainable scale: every learned "
                                                   "method trained with the same data, seed and budget",
                                 description="Trains each learned method on a Fresnel-scaled bench with the same "
                                             "data, seed and budget, scores it on the held-out photographs (8-bit "
                                             "displayed phase) at equal time and equal steps next to the paper's "
                                             "figures; writes reproduction.md/.csv, curves.csv and PSNR plots.")
    budget = reproduce.add_mutually_exclusive_group(required=True)
    budget.add_argument("--minutes", type=float, metavar="M",
                        help="training CPU time per method (this process's CPU time, so other users' load does not "
                             "count)")
    budget.add_argument("--steps", type=_positive_int, metavar="N", help="training steps per method")
    reproduce.add_argument("--size", type=_size, default=(272, 480), metavar="HxW",
                           help="SLM grid; ROI and distance scaled to keep the Fresnel number (default: 272x480)")
    reproduce.add_argument("--methods", type=_names, metavar="LIST",
                           help="comma-separated learned methods, slowest first (default: those of Tables 1, 2, 4)")
    reproduce.add_argument("--colour", "--color", default="red", help="laser channel (default: red, as Table 4)")
    reproduce.add_argument("--data", default="procedural:32+photos:train",
                           help="training images, as for train --data (default: procedural:32+photos:train)")
    reproduce.add_argument("--evaluations", type=_positive_int, default=6,
                           help="evaluations on the held-out photos per method, evenly over the budget (default: 6)")
    reproduce.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default: 1e-3)")
    reproduce.add_argument("--seed", type=int, default=42)
    reproduce.add_argument("--threads", type=_positive_int, metavar="N", help="torch threads (default: torch's)")
    reproduce.add_argument("--no-memory", action="store_true", help="skip the training-step memory subprocesses")
    reproduce.add_argument("--out", "-o", default="bench-out", type=Path, metavar="DIR",
                           help="output folder (default: bench-out)")
    _add_profile(reproduce)
    reproduce.set_defaults(func=_cmd_bench_reproduce)

    train = sub.add_parser(
        "train", help="train a learned hologram method (one model per laser colour)",
        description="Train a learned method on a folder of images (or procedural:N generated images): targets "
                    "prepared as for generate (sRGB -> linear -> ROI -> amplitude -> padded), random flips, Adam, "
                    "loss on the ROI, one model per colour of the profile, validation on held-out images, a "
                    "checkpoint OUT/<method>.pt (+ .json, + .resume.pt) after every epoch and at the end. Under "
                    "`torchrun --nproc_per_node N -m benchctl train ...` it trains with DistributedDataParallel.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    train.add_argument("--method", "-m", required=True,
                       help="learned method to train (`benchctl models` lists them)")
    train.add_argument("--data", required=True, metavar="DIR",
                       help="folder of training images (e.g. DIV2K), procedural:N for N generated images, "
                            "photos:train for the bundled training photographs; join with '+'")
    _add_profile(train)
    train.add_argument("--size", type=_size, metavar="HxW",
                       help="train on this grid instead of the profile's (pitch and distance kept, ROI scaled)")
    train.add_argument("--colours", "--colors", type=_names, metavar="LIST",
                       help="comma-separated laser channels (default: all in the profile)")
    train.add_argument("--epochs", type=_positive_int, default=10, help="passes over the training images (default: 10)")
    train.add_argument("--max-steps", type=_positive_int, metavar="N", help="stop after N steps in all")
    train.add_argument("--lr", type=float, default=5e-4, help="Adam learning rate (default: 5e-4, the paper's)")
    train.add_argument("--loss", choices=("mse", "l2-perceptual"), default="mse",
                       help="mse, or l2-perceptual (MSE + 0.025 VGG19 perceptual, the paper's 1080p loss; needs "
                            "--vgg-weights) (default: mse)")
    train.add_argument("--vgg-weights", type=Path, metavar="FILE",
                       help="local torchvision-format VGG19 state dict for --loss l2-perceptual (never downloaded)")
    train.add_argument("--batch-size", type=_positive_int, default=1, help="images per step and process (default: 1)")
    train.add_argument("--seed", type=int, default=42, help="random seed (default: 42, the paper's)")
    train.add_argument("--val-fraction", type=float, default=0.1,
                       help="fraction of the images held out for validation (default: 0.1)")
    train.add_argument("--weights-dtype", choices=("float32", "float16"), default="float32",
                       help="how the checkpoint stores weights; float16 halves the file (default: float32)")
    train.add_argument("--out", "-o", type=Path, default=Path("out/train"), metavar="DIR",
                       help="folder for the checkpoints (default: out/train)")
    train.add_argument("--model-calibration", metavar="FILE",
                       help="train (or fine-tune, with --resume) through a fitted optical model: 'stored' for the "
                            "profile's (procedures/model_calibration.toml), or an optical-model.json")
    train.add_argument("--resume", type=Path, metavar="CKPT",
                       help="continue from OUT/<method>.resume.pt (exactly) or a checkpoint's weights")
    train.set_defaults(func=_cmd_train)

    profile = sub.add_parser("profile", help="hardware profiles").add_subparsers(
        dest="profile_command", metavar="ACTION", required=True)
    check = profile.add_parser("check", help="validate a profile and print what it describes")
    check.add_argument("path", nargs="?", help="profile TOML path or name (default: simulated)")
    check.set_defaults(func=_cmd_profile_check)

    models = sub.add_parser("models", help="hologram methods with family and parameter count at a grid size")
    models.add_argument("--size", type=_size, metavar="HxW", help="grid (default: the profile's SLM)")
    _add_profile(models)
    models.set_defaults(func=_cmd_models)

    targets = sub.add_parser("targets", help="list the bundled targets")
    targets.set_defaults(func=_cmd_targets)
    run = sub.add_parser(
        "run", help="run a procedure (colour capture, registration, lookup-table calibration, power sweep)",
        description="Run a procedure file on the bench the profile describes. Every run writes a new folder "
                    "OUT/<timestamp>-<name>/ with the profile and procedure as used, versions, device identities, a "
                    "step log, holograms as displayed, RAW frames as captured, images, metrics and report.html. An "
                    "interrupted run leaves emission off and keeps what it captured; --resume finishes it.",
        epilog="procedures: files in procedures/ (TOML, or a Python file with PARAMETERS and plan(); see README). "
               "A .py procedure is code: running, dry-running or resuming it executes it with your rights; run "
               "only procedure files you trust.")
    run.add_argument("procedure", nargs="?", type=Path, help="procedure file (.toml or .py)")
    _add_profile(run)
    run.add_argument("--out", "-o", type=Path, default=Path("runs"), metavar="DIR",
                     help="where run folders are created (default: runs/)")
    run.add_argument("--dry-run", action="store_true",
                     help="check the procedure and profile and print every step; benchctl touches no device and "
                          "writes nothing (a .py procedure's own code still runs)")
    run.add_argument("--resume", type=Path, metavar="RUN_DIR",
                     help="finish an interrupted run without repeating its finished steps")
    run.set_defaults(func=_cmd_run)
    _add_device_commands(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `benchctl` console script; returns the process exit code."""
    from benchctl.devices.lock import set_command
    from benchctl.devices.safety import TerminatedBySignal, signals_interrupt

    args = build_parser().parse_args(argv)
    action = getattr(args, f"{args.command}_command", None) or getattr(args, args.command, None)
    set_command(f"benchctl {args.command}" + (f" {action}" if isinstance(action, str) else ""))
    try:
        with signals_interrupt():
            return args.func(args)
    except BenchctlError as exc:
        print(f"benchctl: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"benchctl: interrupted{f' ({exc})' if str(exc) else ''}", file=sys.stderr)
        return 128 + exc.signum if isinstance(exc, TerminatedBySignal) else 130


if __name__ == "__main__":
    sys.exit(main())
