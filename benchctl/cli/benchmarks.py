"""`benchctl bench ...`: side-by-side measurements (speed against error, propagation, learned methods, the
paper's tables)."""

from __future__ import annotations

import argparse
from pathlib import Path

from benchctl.cli.args import add_profile, grid_size, int_list, name_list, positive_int


def _cmd_bench_speed(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.speed_vs_error import (
        DEFAULT_BUDGETS,
        DEFAULT_TARGETS,
        FULL_BUDGETS,
        resized_profile,
        run_speed_vs_error,
    )
    from benchctl.terminal import ProgressLine
    from benchctl.errors import BadValueError
    from benchctl.profiles import load_profile

    profile = load_profile(args.profile).require("slm", "optics", "laser")
    if args.full and args.size:
        raise BadValueError("--full runs at the profile's own grid; leave out --size")
    size = profile.slm.shape if args.full else args.size or (profile.slm.height // 4, profile.slm.width // 4)
    run_speed_vs_error(resized_profile(profile, size), targets=tuple(args.targets or DEFAULT_TARGETS),
                       methods=tuple(args.methods) if args.methods else None,
                       budgets=args.iterations or (FULL_BUDGETS if args.full else DEFAULT_BUDGETS),
                       colours=args.colours, seed=args.seed, out_dir=Path(args.out), progress=ProgressLine)
    return 0


def _cmd_bench_propagation(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.propagation import PAPER_SIZES, run_propagation_bench
    from benchctl.files import ensure_dir, write_csv
    from benchctl.profiles import load_profile

    rows = run_propagation_bench(load_profile(args.profile), sizes=args.size or PAPER_SIZES, repeats=args.repeats)
    if args.out:
        print(f"wrote {write_csv(ensure_dir(Path(args.out)) / 'propagation.csv', rows)}")
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


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add this group's sub-commands to the `benchctl` sub-parsers (importing nothing heavy)."""
    bench = sub.add_parser("bench", help="benchmarks: speed against error").add_subparsers(
        dest="bench", metavar="BENCH", required=True)
    speed = bench.add_parser("speed-vs-error", help="seconds per frame against PSNR/SSIM for each method and budget",
                             description="Runs every hologram method at several iteration budgets on the targets, "
                                         "prints a table and writes speed_vs_error.csv (+ .png with matplotlib).")
    speed.add_argument("--targets", nargs="+", metavar="TARGET", help="targets (default: chart:siemens chart:bars "
                                                                     "chart:text and the held-out photographs)")
    speed.add_argument("--methods", type=name_list, metavar="LIST",
                       help="comma-separated methods (default: all classical ones, and learned ones whose "
                            "shipped checkpoint fits the benchmark's grid, alone and refined: <name>+sgd)")
    speed.add_argument("--iterations", type=int_list, metavar="LIST",
                       help="iteration budgets for iterative methods (default: 10,50,200,500; 10,50 with --full)")
    speed.add_argument("--size", type=grid_size, metavar="HxW",
                       help="SLM grid for the benchmark; ROI and distance scaled to keep the Fresnel number "
                            "(default: a quarter of the profile's grid per axis)")
    speed.add_argument("--full", action="store_true",
                       help="the profile's own geometry (the paper's 1088x1920 on the simulated profile): slow")
    speed.add_argument("--colours", type=name_list, metavar="LIST",
                       help="comma-separated laser channels, e.g. green (default: all in the profile)")
    speed.add_argument("--seed", type=int, default=0)
    speed.add_argument("--out", "-o", default="bench-out", metavar="DIR", help="output folder (default: bench-out)")
    add_profile(speed)
    speed.set_defaults(func=_cmd_bench_speed)

    prop = bench.add_parser("propagation", help="padding modes: time vs bare FFT and error vs a float64 reference",
                            description="For each padding mode, colour and grid: the plan, the time of one "
                                        "propagation, its ratio to a bare fft2+ifft2 of the same padded grid and "
                                        "the relative L2 error on the ROI against a converged float64 propagation.")
    prop.add_argument("--size", type=grid_size, nargs="+", metavar="HxW",
                      help="grids to measure (default: 1088x1920 2160x3840)")
    prop.add_argument("--repeats", type=positive_int, default=5, help="timed repeats per case (default: 5)")
    prop.add_argument("--out", "-o", metavar="DIR", help="also write propagation.csv here")
    add_profile(prop)
    prop.set_defaults(func=_cmd_bench_propagation)

    learned = bench.add_parser("learned", help="learned methods side by side: parameters, inference time, training "
                                               "memory, PSNR/SSIM, ratios to the baseline network",
                               description="Per learned method, measured in one run: trainable parameters, inference "
                                           "seconds per frame, peak memory of one training step (a fresh subprocess "
                                           "per model on CPU; the allocator's peak on CUDA), PSNR/SSIM where a "
                                           "checkpoint fits, and ratios against holonet / ccnn. Writes learned.csv.")
    learned.add_argument("--size", type=grid_size, metavar="HxW",
                         help="grid (default: the profile's); pitch and distance kept, ROI scaled, as for training")
    learned.add_argument("--methods", type=name_list, metavar="LIST",
                         help="comma-separated learned methods (default: all; the family baselines are added)")
    learned.add_argument("--checkpoint", type=Path, nargs="+", default=[], metavar="CKPT",
                         help="trained checkpoints to score (default: the shipped ones that fit the grid)")
    learned.add_argument("--repeats", type=positive_int, default=3, help="timed inference runs (default: 3)")
    learned.add_argument("--inference-only", action="store_true", help="skip the training-step memory subprocesses")
    learned.add_argument("--out", "-o", default="bench-out", type=Path, metavar="DIR",
                         help="output folder (default: bench-out)")
    add_profile(learned)
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
    budget.add_argument("--steps", type=positive_int, metavar="N", help="training steps per method")
    reproduce.add_argument("--size", type=grid_size, default=(272, 480), metavar="HxW",
                           help="SLM grid; ROI and distance scaled to keep the Fresnel number (default: 272x480)")
    reproduce.add_argument("--methods", type=name_list, metavar="LIST",
                           help="comma-separated learned methods, slowest first (default: those of Tables 1, 2, 4)")
    reproduce.add_argument("--colour", "--color", default="red", help="laser channel (default: red, as Table 4)")
    reproduce.add_argument("--data", default="procedural:32+photos:train",
                           help="training images, as for train --data (default: procedural:32+photos:train)")
    reproduce.add_argument("--evaluations", type=positive_int, default=6,
                           help="evaluations on the held-out photos per method, evenly over the budget (default: 6)")
    reproduce.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default: 1e-3)")
    reproduce.add_argument("--seed", type=int, default=42)
    reproduce.add_argument("--threads", type=positive_int, metavar="N", help="torch threads (default: torch's)")
    reproduce.add_argument("--no-memory", action="store_true", help="skip the training-step memory subprocesses")
    reproduce.add_argument("--out", "-o", default="bench-out", type=Path, metavar="DIR",
                           help="output folder (default: bench-out)")
    add_profile(reproduce)
    reproduce.set_defaults(func=_cmd_bench_reproduce)
