"""``palette-recolor``: a weight stack and an edited palette -> recoloured images, everywhere
or inside a selection."""

from __future__ import annotations

import sys
from pathlib import Path

from ..palette_file import read_palette_json
from ..recolor import recolor_stack
from ..selection import Selection, parse_near
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
    where = parser.add_argument_group(
        "local edits", "recolour only a selection of each image; outside it every pixel "
        "keeps its unedited colour (docs/selections.md)")
    choice = where.add_mutually_exclusive_group()
    choice.add_argument("--mask", metavar="MASK",
                        help="mask image (grey or alpha: 255 inside) for every image, or a "
                             "folder of masks named like the images")
    choice.add_argument("--select-colour", type=int, metavar="K",
                        help="the pixels whose weight for palette colour K (from 0) is at "
                             "least --threshold")
    choice.add_argument("--select-near", metavar="#RRGGBB",
                        help="the pixels whose colour lies within --distance of this one")
    where.add_argument("--threshold", type=float, default=0.5,
                       help="weight that --select-colour needs (default 0.5)")
    where.add_argument("--distance", type=float, default=0.1,
                       help="RGB distance in [0, 1] for --select-near (default 0.1)")
    where.add_argument("--feather", type=float, default=0.0, metavar="PIXELS",
                       help="soften the selection's edge by a Gaussian of this many pixels")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _run(build_parser().parse_args(argv)))


def _run(args) -> int:
    stack = read_stack(args.stack)
    palette = read_palette_json(args.palette, k=len(stack.palette))
    selection = None
    if args.mask or args.select_colour is not None or args.select_near:
        selection = Selection(mask=args.mask and Path(args.mask), colour=args.select_colour,
                              near=args.select_near and parse_near(args.select_near),
                              threshold=args.threshold, distance=args.distance,
                              feather=args.feather)
    written = recolor_stack(stack, palette, args.output, args.force, args.frames, selection)
    where = "" if selection is None else " (inside the selection only)"
    print(f"wrote {len(written)} recoloured files to {args.output}{where}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
