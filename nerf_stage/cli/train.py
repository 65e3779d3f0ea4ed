"""``nerf-stage train``: a weight NeRF on a dataset and its weight stack
(``trainer.train_capture``)."""

from __future__ import annotations

from palette_core.cli import add_config_arguments, config_from_args
from palette_core.stack import DEFAULT_STACK

from ..train.config import CONFIG_ENV, TrainConfig


def add(commands, defaults: TrainConfig) -> None:
    train = commands.add_parser(
        "train", help="train a weight NeRF on a dataset and its weight stack",
        description="Train a NeRF whose colour head outputs the weight stack's M channels "
                    "(PaletteNeRF). Writes RUNDIR/config.json and RUNDIR/checkpoint.pt. "
                    "Every field of the training config is a flag; their defaults can come "
                    f"from a JSON file named by the environment variable {CONFIG_ENV}.")
    train.add_argument("data", metavar="DATADIR", nargs="?", default=".",
                       help="Blender or nerfstudio dataset folder (default: this folder)")
    train.add_argument("--weights", default=None, metavar="STACK",
                       help="weight stack (.npz) of the training frames (default: "
                            f"DATADIR/{DEFAULT_STACK}, where palette-decompose images/ run in "
                            "DATADIR and nerf-stage simulate put it)")
    train.add_argument("-o", "--output", metavar="RUNDIR", default=None,
                       help="run folder (default: DATADIR-BACKBONE beside DATADIR)")
    train.add_argument("--frames-outside", action="store_true",
                       help="read frames whose file_path lies outside DATADIR (absolute, or "
                            "climbing out with ..); refused by default")
    train.add_argument("--downscale", type=int, default=1, metavar="N",
                       help="train on images N times smaller than the files (the mean of each "
                            "N x N block; the weight stack may be of either size); render and "
                            "eval read them so too (default 1)")
    add_config_arguments(train, defaults)
    again = train.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true", help="continue RUNDIR's checkpoint")
    again.add_argument("--force", action="store_true", help="start RUNDIR afresh")
    train.set_defaults(run=run)


def run(args) -> int:
    from ..train.checkpoint import CHECKPOINT
    from ..train.trainer import peak_memory, train_capture

    config = config_from_args(TrainConfig, args)
    done = train_capture(args.data, config, args.weights, args.output, args.frames_outside,
                         args.downscale, args.resume, args.force)
    dataset, log, config = done.dataset, done.run.record.log, done.run.config
    print(f"dataset: {dataset.root} ({dataset.layout} layout, {len(dataset.names)} frames, "
          f"{len(dataset.indices('train'))} for training)")
    print(f"weights: {done.weights}")
    asked = f" of the {60 * config.minutes:.0f} s asked" if config.minutes else ""
    print(f"trained {config.backbone} ({config.strategy}) for {len(log)} iterations in "
          f"{log[-1]['seconds']:.0f} s{asked}, last batch PSNR {log[-1]['psnr']:.2f} dB, "
          f"peak memory {peak_memory(done.run.device)}")
    print(f"wrote {done.rundir / CHECKPOINT}; next: nerf-stage render {done.rundir} -o DIR")
    return 0
