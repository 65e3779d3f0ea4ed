"""``palette-recolor``: a weight stack and an edited palette -> recoloured images."""

from __future__ import annotations

import sys

from ..palette_file import read_palette_json
from ..recolor import recolor_stack
from ..stack import read_stack
from . import ArgumentParser, run_cli

PROG = "palette-recolor"


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog=PROG, description="Recolour every image of a weight stack "
                            "with an edited palette.")
    parser.add_argument("stack", help="weight stack (.npz or .zarr) from palette-decompose")
    parser.add_argument("--palette", required=True,
                        help='palette JSON: {"palette": ["#rrggbb", ...]}, as many colours as '
                             "the stack's palette")
    parser.add_argument("-o", "--output", required=True, metavar="DIR",
                        help="folder for the recoloured images (same names as the inputs)")
    parser.add_argument("--frames", action="store_true",
                        help="write the frames of videos as PNGs instead of videos")
    parser.add_argument("--force", action="store_true", help="overwrite existing images")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _run(build_parser().parse_args(argv)))


def _run(args) -> int:
    stack = read_stack(args.stack)
    palette = read_palette_json(args.palette, k=len(stack.palette))
    written = recolor_stack(stack, palette, args.output, args.force, args.frames)
    print(f"wrote {len(written)} recoloured files to {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
