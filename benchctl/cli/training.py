"""`benchctl train`: train a learned hologram method."""

from __future__ import annotations

import argparse
from pathlib import Path

from benchctl.cli.args import EPILOG, add_device, add_profile, count, grid_size, name_list, positive_int, seed_number


def _cmd_train(args: argparse.Namespace) -> int:
    from benchctl.profiles import load_profile
    from benchctl.training.training import TrainSettings, run_train

    settings = TrainSettings(method=args.method, data=args.data, size=args.size,
                             colours=tuple(args.colours) if args.colours else None, epochs=args.epochs, lr=args.lr,
                             loss=args.loss, vgg_weights=args.vgg_weights, batch_size=args.batch_size, seed=args.seed,
                             val_fraction=args.val_fraction, max_steps=args.max_steps,
                             weights_dtype=args.weights_dtype, model_calibration=args.model_calibration,
                             ema=args.ema, warmup=args.warmup, decay=args.decay, device=args.device)
    run_train(load_profile(args.profile), settings, args.out, resume=args.resume)
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add this group's sub-commands to the `benchctl` sub-parsers (importing nothing heavy)."""
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
    add_profile(train)
    train.add_argument("--size", type=grid_size, metavar="HxW",
                       help="train on this grid instead of the profile's (pitch and distance kept, ROI scaled)")
    train.add_argument("--colours", "--colors", type=name_list, metavar="LIST",
                       help="comma-separated laser channels (default: all in the profile)")
    train.add_argument("--epochs", type=positive_int, default=10, help="passes over the training images (default: 10)")
    train.add_argument("--max-steps", type=positive_int, metavar="N", help="stop after N steps in all")
    train.add_argument("--lr", type=float, default=5e-4, help="Adam learning rate (default: 5e-4, the paper's)")
    train.add_argument("--warmup", type=count, default=0, metavar="STEPS",
                       help="linear learning-rate warm-up over the first STEPS steps (default: 0, the paper's)")
    train.add_argument("--decay", choices=("none", "cosine"), default="none",
                       help="learning-rate decay after the warm-up: none, or cosine to zero at the last step "
                            "(--epochs or --max-steps) (default: none, the paper's)")
    add_device(train)
    train.add_argument("--ema", type=float, metavar="DECAY",
                       help="keep an exponential moving average of the weights with this per-step decay (e.g. 0.99: "
                            "about the last 100 steps); validation and the checkpoint use the average, the raw "
                            "weights train on (.resume.pt holds both) (default: off, the paper's)")
    train.add_argument("--loss", choices=("mse", "l2-perceptual"), default="mse",
                       help="mse, or l2-perceptual (MSE + 0.025 VGG19 perceptual, the paper's 1080p loss; needs "
                            "--vgg-weights) (default: mse)")
    train.add_argument("--vgg-weights", type=Path, metavar="FILE",
                       help="local torchvision-format VGG19 state dict for --loss l2-perceptual (never downloaded)")
    train.add_argument("--batch-size", type=positive_int, default=1, help="images per step and process (default: 1)")
    train.add_argument("--seed", type=seed_number, default=42,
                       help="random seed, 0 to 2^32-1 (default: 42, the paper's)")
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
