"""``nerf-stage``: simulate scenes or pose photos; train weight NeRFs, render and recolour
them, evaluate, bake and export splats. Each command parses its flags, makes one library
call and prints what it did (one module a command).

The torch-based commands import torch only when they run, so ``simulate`` works
without the ``nerf`` extra.
"""

from __future__ import annotations

import sys

from palette_core.cli import ArgumentParser, run_cli

from ..train.config import TrainConfig

PROG = "nerf-stage"


def build_parser(train_defaults: TrainConfig | None = None) -> ArgumentParser:
    """The parser of every command; ``train``'s flags default to ``train_defaults`` (the
    dataclass's defaults when None)."""
    from . import poses, render, simulate, splats, train

    parser = ArgumentParser(prog=PROG, description="NeRF stage of the palette toolkit.")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                     parser_class=ArgumentParser)
    simulate.add(commands)
    poses.add(commands)
    train.add(commands, train_defaults or TrainConfig())
    render.add_render(commands)
    render.add_eval(commands)
    splats.add(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _dispatch(argv))


def _dispatch(argv) -> int:
    argv = sys.argv[1:] if argv is None else argv
    # Only train reads CONFIG_ENV: a bad file there must not break the other commands.
    defaults = TrainConfig.defaults() if argv[:1] == ["train"] else None
    args = build_parser(defaults).parse_args(argv)
    return args.run(args)
