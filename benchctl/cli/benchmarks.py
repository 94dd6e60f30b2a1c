"""`benchctl bench ...`: side-by-side measurements (speed against error, propagation, learned methods, the
paper's tables)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from benchctl.cli.args import (
    add_device,
    add_profile,
    count,
    grid_size,
    int_list,
    name_list,
    positive_int,
    seconds,
    seed_number,
    whole_number,
)


def _cmd_bench_speed(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.speed_vs_error import (
        DEFAULT_BUDGETS,
        DEFAULT_TARGETS,
        FULL_BUDGETS,
        resized_profile,
        run_speed_vs_error,
    )
    from benchctl.errors import BadValueError
    from benchctl.profiles import load_profile
    from benchctl.terminal import ProgressLine

    profile = load_profile(args.profile).require("slm", "optics", "laser")
    if args.full and args.size:
        raise BadValueError("--full runs at the profile's own grid; leave out --size")
    slm = profile.section("slm")
    size = slm.shape if args.full else args.size or (slm.height // 4, slm.width // 4)
    run_speed_vs_error(resized_profile(profile, size), targets=tuple(args.targets or DEFAULT_TARGETS),
                       methods=tuple(args.methods) if args.methods else None,
                       budgets=args.iterations or (FULL_BUDGETS if args.full else DEFAULT_BUDGETS),
                       colours=args.colours, seed=args.seed, out_dir=Path(args.out), progress=ProgressLine)
    return 0


def _cmd_bench_propagation(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.propagation import PAPER_SIZES, run_multiplane_bench, run_propagation_bench
    from benchctl.files import ensure_dir, write_csv
    from benchctl.profiles import load_profile

    profile = load_profile(args.profile)
    sizes = args.size or PAPER_SIZES
    rows = [] if args.planes_only else run_propagation_bench(profile, sizes=sizes, repeats=args.repeats)
    planes = run_multiplane_bench(profile, sizes=sizes, planes=args.planes, repeats=args.repeats) if args.planes else []
    if args.out:
        folder = ensure_dir(Path(args.out))
        if rows:
            print(f"wrote {write_csv(folder / 'propagation.csv', rows)}")
        if planes:
            print(f"wrote {write_csv(folder / 'multiplane.csv', planes)}")
    return 0


def _cmd_bench_depth(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.depth import DEFAULT_SCENES, run_depth_bench
    from benchctl.benchmarks.speed_vs_error import resized_profile
    from benchctl.files import ensure_dir, write_csv
    from benchctl.profiles import load_profile

    profile = load_profile(args.profile).require("slm", "optics", "laser")
    slm = profile.section("slm")
    size = args.size or (slm.height // 4, slm.width // 4)
    rows = run_depth_bench(resized_profile(profile, size), scenes=args.scenes or DEFAULT_SCENES,
                           counts=args.planes, method=args.method, iterations=args.iterations,
                           colour=args.colour)
    if args.out:
        print(f"wrote {write_csv(ensure_dir(Path(args.out)) / 'depth.csv', rows)}")
    return 0


def _cmd_bench_learned(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.learned import MEMORY_TABLE_METHODS, run_learned_bench, run_memory_table
    from benchctl.errors import BadValueError
    from benchctl.profiles import load_profile

    if args.grids:
        if args.size:
            raise BadValueError("--grids measures training memory on several grids; leave out --size")
        run_memory_table(load_profile(args.profile), grids=args.grids, methods=args.methods or MEMORY_TABLE_METHODS,
                         memory_cap_gib=args.memory_cap, out_dir=args.out)
        return 0
    run_learned_bench(load_profile(args.profile), size=args.size, methods=args.methods, checkpoints=args.checkpoint,
                      repeats=args.repeats, training_memory=not args.inference_only, out_dir=args.out)
    return 0


def _cmd_bench_learned_depth(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.learned_depth import run_learned_depth_bench
    from benchctl.profiles import load_profile

    run_learned_depth_bench(load_profile(args.profile), args.checkpoint, scenes=args.scenes, colour=args.colour,
                            planes=args.planes, sgd_iterations=args.sgd_iterations, out_dir=args.out)
    return 0


def _cmd_bench_genicam(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.genicam import run_genicam_bench

    height, width = args.size
    result = run_genicam_bench(width, height, frames=args.frames, frame_rate=args.frame_rate)
    print("\n".join(result.lines()))
    return 0


def _cmd_bench_reproduce(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.reproduce import DEFAULT_METHODS, new_plan, reproduce_command, run_reproduction
    from benchctl.benchmarks.reproduce_report import write_report
    from benchctl.errors import BadValueError
    from benchctl.profiles import load_profile

    if args.report:
        write_report(args.report)
        return 0
    if args.resume:
        if args.out:
            raise BadValueError("--resume continues the run in its own folder; leave out --out")
        run_reproduction(args.resume, jobs=args.jobs, jobs_per_gpu=args.jobs_per_gpu, memory=not args.no_memory,
                         wait=args.wait)
        return 0
    if not args.out:
        raise BadValueError("give --out DIR for a new run (or --resume DIR / --report DIR for an existing one)")
    methods = list(DEFAULT_METHODS) if args.methods is None else args.methods  # --methods "" is refused, not all
    settings = dict(size=args.size, methods=methods, seeds=args.seeds, ablation_seeds=args.ablation_seeds,
                    colour=args.colour, data=args.data, lr=args.lr, max_steps=args.max_steps, min_steps=args.min_steps,
                    min_gain_db=args.min_gain, patience=args.patience, iris_test=not args.no_iris_test,
                    threads=args.threads, warmup=args.warmup, decay=args.decay, held_out=args.held_out,
                    device=args.device,
                    slurm={"partition": args.slurm, "time_min": args.slurm_time} if args.slurm else None)
    command = reproduce_command(args.profile, args.out, jobs=args.jobs, jobs_per_gpu=args.jobs_per_gpu, **settings)
    new_plan(args.out, load_profile(args.profile), command=command, **settings)
    run_reproduction(args.out, jobs=args.jobs, jobs_per_gpu=args.jobs_per_gpu, memory=not args.no_memory,
                     wait=args.wait)
    return 0


def _cmd_bench_sweep(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.sweep import new_sweep, run_sweep
    from benchctl.errors import BadValueError
    from benchctl.profiles import load_profile

    if args.resume:
        if args.out:
            raise BadValueError("--resume continues the sweep in its own folder; leave out --out")
        settings = json.loads((args.resume / "sweep-settings.json").read_text()) \
            if (args.resume / "sweep-settings.json").is_file() else {}
        run_sweep(args.resume, load_profile(settings.get("profile") or args.profile))
        return 0
    if not args.out:
        raise BadValueError("give --out DIR for a new sweep (or --resume DIR to continue one)")
    if not args.method:
        raise BadValueError("give --method, the learned method to tune (`benchctl models` lists them)")
    profile = load_profile(args.profile)
    recipe = {"size": args.size, "data": args.data, "held_out": args.held_out, "colour": args.colour,
              "max_steps": args.max_steps, "min_steps": min(args.min_steps, args.max_steps),
              "min_gain_db": args.min_gain, "patience": args.patience, "threads": args.threads, "device": args.device,
              "iris_test": False}
    new_sweep(args.out, profile, method=args.method, trials=args.trials, lr=args.lr_range, warmup=args.warmup_choices,
              decay=args.decay_choices, seed=args.seed, recipe=recipe)
    run_sweep(args.out, profile)
    return 0


def add_recipe(parser: argparse.ArgumentParser, *, max_steps: int, min_steps: int) -> None:
    """The options of a reproduction job's recipe that `bench reproduce` and `bench sweep` share."""
    parser.add_argument("--size", type=grid_size, default=(136, 240), metavar="HxW",
                        help="SLM grid; ROI and distance scaled to keep the Fresnel number (default: 136x240)")
    parser.add_argument("--colour", "--color", default="red", help="laser channel (default: red, as Table 4)")
    parser.add_argument("--data", default="procedural:32+photos:train",
                        help="training images, as for train --data (default: procedural:32+photos:train)")
    parser.add_argument("--held-out", default="photos:eval", metavar="DATA",
                        help="images the tables score (never trained on), as for --data (default: photos:eval, the "
                             "four held-out photographs)")
    parser.add_argument("--max-steps", type=positive_int, default=max_steps, metavar="N",
                        help=f"step cap per job, where a decay ends (default: {max_steps})")
    parser.add_argument("--min-steps", type=positive_int, default=min_steps, metavar="N",
                        help=f"no convergence test before this step (default: {min_steps})")
    parser.add_argument("--min-gain", type=float, default=0.2, metavar="DB",
                        help="stop once the validation score gains less than this per doubling of steps (default: "
                             "0.2)")
    parser.add_argument("--patience", type=positive_int, default=2, metavar="N",
                        help="stop once N power-of-two steps in a row each gained less than --min-gain (default: 2: "
                             "one dip of a noisy curve does not end a job)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads per job (default: 1)")


def lr_range(text: str) -> tuple[float, float]:
    """LOW:HIGH learning rates, e.g. 1e-4:2e-3."""
    try:
        low, high = (float(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW:HIGH such as 1e-4:2e-3, got {text!r}") from None
    return low, high


def _cmd_bench_console(args: argparse.Namespace) -> int:
    from benchctl.benchmarks.console import run_console_bench

    run_console_bench(args.profile, seconds=args.seconds, repeats=args.repeats, out=args.out)
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add this group's sub-commands to the `benchctl` sub-parsers (importing nothing heavy)."""
    bench = sub.add_parser("bench", help="benchmarks: speed against error, propagation, learned methods, the paper's "
                                         "tables").add_subparsers(
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
    prop.add_argument("--planes", type=whole_number(0, 64), default=8, metavar="K",
                      help="also time one field propagated to K planes over the profile's depth range against K "
                           "independent propagations, with both errors (default: 8; 0: leave out)")
    prop.add_argument("--planes-only", action="store_true", help="only the multi-plane comparison")
    prop.add_argument("--out", "-o", metavar="DIR", help="also write propagation.csv (and multiplane.csv) here")
    add_profile(prop)
    prop.set_defaults(func=_cmd_bench_propagation)

    depth = bench.add_parser("depth", help="scenes with depth: focal-stack PSNR against the number of planes, the "
                                           "planes --planes auto chooses, multi-plane against 2D SGD",
                             description="Per bundled scene, the method's hologram at each K of --planes evenly over "
                                         "the scene's depth and at the planes --planes auto chooses, each judged on "
                                         "the same all-in-focus image (from a 64-plane focal stack) and timed; then "
                                         "multi-plane SGD on rgbd:two-planes against 2D SGD on each plane's image "
                                         "alone. One colour, scaled bench as speed-vs-error, no SLM quantisation.")
    depth.add_argument("--scenes", nargs="+", metavar="SCENE", help="rgbd scenes (default: all bundled ones)")
    depth.add_argument("--planes", type=int_list, default=tuple(range(1, 17)), metavar="LIST",
                       help="comma-separated plane counts K to measure (default: 1,2,...,16)")
    depth.add_argument("--method", "-m", default="sgd", help="a method that makes focal stacks (default: sgd)")
    depth.add_argument("--iterations", "-n", type=positive_int, default=100, help="iterations (default: 100)")
    depth.add_argument("--colour", default="green", help="laser channel (default: green)")
    depth.add_argument("--size", type=grid_size, metavar="HxW",
                       help="SLM grid; ROI, distance and depth range scaled (default: a quarter of the profile's grid "
                            "per axis)")
    depth.add_argument("--out", "-o", metavar="DIR", help="also write depth.csv here")
    add_profile(depth)
    depth.set_defaults(func=_cmd_bench_depth)

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
    learned.add_argument("--grids", type=grid_size, nargs="+", metavar="HxW",
                         help="instead: the training-step memory and time of each method on each of these grids (e.g. "
                              "1088x1920 2176x3840 4352x7680, the paper's), each step in a subprocess capped at "
                              "--memory-cap; writes learned_memory.csv")
    learned.add_argument("--memory-cap", type=float, default=20.0, metavar="GIB",
                         help="address-space cap of each --grids subprocess, in GiB: a step that needs more is "
                              "reported as out of memory (default: 20)")
    learned.add_argument("--out", "-o", default="bench-out", type=Path, metavar="DIR",
                         help="output folder (default: bench-out)")
    add_profile(learned)
    learned.set_defaults(func=_cmd_bench_learned)

    depth = bench.add_parser(
        "learned-depth", help="networks for scenes with depth (holonet3d*) against layered DPAC and multi-plane SGD "
                              "on held-out scenes: per-plane in-focus PSNR / SSIM, over seeds",
        description="On the bench the checkpoints were trained for, per held-out scene (the bundled rgbd: scenes): "
                    "each checkpoint's network, layered DPAC and multi-plane SGD (the focal-stack loss, from layered "
                    "DPAC, exactly --sgd-iterations), each plane scored inside its in-focus region "
                    "(amplitude PSNR / SSIM, unquantised phase) and timed; several checkpoints of one method (seeds) "
                    "give mean +- standard deviation. Writes learned_depth.csv and learned_depth_summary.csv.")
    depth.add_argument("--checkpoint", type=Path, nargs="+", required=True, metavar="CKPT",
                       help="trained holonet3d* checkpoints (one bench and depth range), e.g. one per method and seed")
    depth.add_argument("--scenes", type=name_list, metavar="LIST",
                       help="comma-separated rgbd: scenes (default: every bundled one)")
    depth.add_argument("--colour", "--color", metavar="NAME", help="laser colour (default: the checkpoints' first)")
    depth.add_argument("--planes", type=positive_int, default=5, metavar="K",
                       help="planes of a scene with continuous depth (a layered scene: its own depths) (default: 5)")
    depth.add_argument("--sgd-iterations", type=whole_number(0), default=500, metavar="N",
                       help="multi-plane SGD iterations, no early stop (default: 500, SGD's)")
    depth.add_argument("--out", "-o", default="bench-out", type=Path, metavar="DIR",
                       help="output folder (default: bench-out)")
    add_profile(depth)
    depth.set_defaults(func=_cmd_bench_learned_depth)

    genicam = bench.add_parser("genicam", help="frames per second into numpy from Aravis's fake camera, and the "
                                               "genicam driver's overhead per frame",
                               description="Streams Aravis's in-process fake camera free running (BayerRG8) and "
                                           "turns every buffer into a numpy frame as the genicam driver does; prints "
                                           "sustained fps, dropped (frame-id gaps) and incomplete frames, and the "
                                           "driver's time per frame (buffer -> numpy, numpy -> DNG). Needs the "
                                           "genicam extra.")
    for flags, options in ((("--size",), {"type": grid_size, "default": (2048, 2048), "metavar": "HxW",
                                          "help": "region of the fake camera (default: 2048x2048, its sensor)"}),
                           (("--frames",), {"type": positive_int, "default": 100, "help": "default: 100"}),
                           (("--frame-rate",), {"type": float, "metavar": "FPS",
                                                "help": "the fake camera's frame rate (default: its own, 25)"})):
        genicam.add_argument(*flags, **options)
    genicam.set_defaults(func=_cmd_bench_genicam)

    reproduce = bench.add_parser(
        "reproduce", help="the paper's quality tables: every learned method trained until its curve flattens, "
                          "several seeds, resumable",
        description="Trains each learned method of the paper's Tables 1, 2 and 4 on a Fresnel-scaled bench (same "
                    "data and recipe: Adam at the paper's lr 5e-4, batch 1, flips) until its validation score gains "
                    "less than --min-gain dB per doubling of steps (or --max-steps), with every seed of --seeds "
                    "for the main networks and --ablation-seeds for the ablations, --jobs subprocesses at a time. "
                    "Scores on the held-out photographs (8-bit displayed phase) where training ended, at equal "
                    "steps and at equal time, next to the paper's figures; training-step memory and inference "
                    "time per method; writes reproduction.md/.csv, comparisons.csv, curves.csv and plots into the "
                    "run folder. Interrupted, `--resume DIR` continues it: finished jobs are never retrained.")
    reproduce.add_argument("--out", "-o", type=Path, metavar="DIR", help="folder of a new run")
    reproduce.add_argument("--resume", type=Path, metavar="DIR", help="continue the run in DIR (its own settings)")
    reproduce.add_argument("--report", type=Path, metavar="DIR",
                           help="write the report from the finished jobs in DIR (or from its CSVs once the jobs "
                                "are deleted) and exit, training nothing: the table, the paper's claims with paired "
                                "95%% intervals and verdicts, per-image scores, curves and plots")
    reproduce.add_argument("--methods", type=name_list, metavar="LIST",
                           help="comma-separated learned methods (default: those of Tables 1, 2, 4)")
    reproduce.add_argument("--seeds", type=int_list, default=(42, 43, 44), metavar="LIST",
                           help="seeds of holonet, its x2 / x4 / pyramid, ccnn and ccnn-dcm4 (default: 42,43,44)")
    reproduce.add_argument("--ablation-seeds", type=int_list, metavar="LIST",
                           help="seeds of the ablations (default: the first of --seeds)")
    reproduce.add_argument("--lr", type=float, default=5e-4, help="Adam learning rate (default: 5e-4, the paper's)")
    reproduce.add_argument("--warmup", type=count, default=0, metavar="STEPS",
                           help="linear learning-rate warm-up over the first STEPS steps (default: 0, the paper's)")
    reproduce.add_argument("--decay", choices=("none", "cosine"), default="none",
                           help="learning-rate decay after the warm-up: none, or cosine to zero at --max-steps "
                                "(default: none, the paper's)")
    reproduce.add_argument("--no-iris-test", action="store_true",
                           help="skip training holonet-dcm2 and holonet-lowdef2 again on the bench without its iris")
    add_recipe(reproduce, max_steps=8192, min_steps=1024)
    reproduce.add_argument("--jobs", type=positive_int, default=2, help="jobs trained at a time (default: 2)")
    add_device(reproduce)
    reproduce.add_argument("--jobs-per-gpu", type=positive_int, default=1, metavar="K",
                           help="on GPUs: K jobs at a time per GPU, each pinned to one GPU by CUDA_VISIBLE_DEVICES "
                                "(--jobs is the CPU's count) (default: 1)")
    reproduce.add_argument("--no-memory", action="store_true", help="skip the training-step memory subprocesses")
    reproduce.add_argument("--slurm", metavar="PARTITION",
                           help="run the plan's jobs as one SLURM job array in PARTITION (through submitit; the run "
                                "folder must be on a file system the nodes share); --resume DIR then collects what "
                                "finished and submits again what left the queue unfinished")
    reproduce.add_argument("--slurm-time", type=positive_int, default=1440, metavar="MIN",
                           help="SLURM time limit per job in minutes: a job that reaches it is requeued and "
                                "continues from its saved state (default: 1440)")
    reproduce.add_argument("--wait", action="store_true",
                           help="with --slurm (or --resume of a SLURM run): wait until every job has finished")
    add_profile(reproduce)
    reproduce.set_defaults(func=_cmd_bench_reproduce)

    sweep = bench.add_parser(
        "sweep", help="hyperparameter search (lr, warm-up, decay) for one learned method through Optuna, resumable",
        description="Optuna's TPE sampler proposes a learning rate (log-uniform in --lr-range), a warm-up and a "
                    "decay per trial; each trial trains one bench reproduce job (its own seed: --seed + the trial's "
                    "number) until its validation score flattens, and its best validation PSNR is the objective. "
                    "The study is kept in DIR/sweep.journal (Optuna's file journal); --resume DIR continues an "
                    "interrupted trial exactly and runs the rest. `benchctl runs compare DIR` shows the trials.")
    sweep.add_argument("--method", "-m", help="learned method to tune (a new sweep needs one)")
    sweep.add_argument("--trials", type=positive_int, default=8, help="trials to finish (default: 8)")
    sweep.add_argument("--lr-range", type=lr_range, default=(1e-4, 2e-3), metavar="LOW:HIGH",
                       help="learning rates tried, log-uniform (default: 1e-4:2e-3)")
    sweep.add_argument("--warmup-choices", type=lambda t: [int(v) for v in t.split(",")], default=[0, 64, 256],
                       metavar="LIST", help="warm-up step counts tried (default: 0,64,256)")
    sweep.add_argument("--decay-choices", type=name_list, default=["none", "cosine"], metavar="LIST",
                       help="decays tried (default: none,cosine)")
    sweep.add_argument("--seed", type=seed_number, default=42,
                       help="the first trial's seed (trial n trains with seed + n) and the sampler's (default: 42)")
    add_recipe(sweep, max_steps=2048, min_steps=512)
    add_device(sweep)
    sweep.add_argument("--out", "-o", type=Path, metavar="DIR", help="folder of a new sweep")
    sweep.add_argument("--resume", type=Path, metavar="DIR", help="continue the sweep in DIR")
    add_profile(sweep)
    sweep.set_defaults(func=_cmd_bench_sweep)

    console = bench.add_parser("console", help="the live console from outside: preview fps, change-to-frame latency, "
                                               "status latency during an SGD hologram (a console server is started)")
    console.add_argument("--seconds", type=seconds, default=10.0, help="how long frames are counted (default 10)")
    console.add_argument("--repeats", type=positive_int, default=5, help="changes timed per kind (default 5)")
    console.add_argument("--out", "-o", type=Path, metavar="DIR", help="also write console.json there")
    add_profile(console)
    console.set_defaults(func=_cmd_bench_console)
