"""``palette-recolor``: a weight stack and an edited palette -> recoloured images, everywhere
or inside a selection; a splat stack -> a recoloured splat file (``splat_files.commands``)."""

from __future__ import annotations

from pathlib import Path
from typing import NoReturn

import numpy as np

from ..edit_file import check_edits_writable, read_edits, write_edits
from ..errors import InputError
from ..palette_file import read_palette_json
from ..recolor import recolor_stack
from ..selection import LocalEdit, Selection, parse_near
from ..stack import read_stack
from . import ArgumentParser, exit_without_teardown, run_cli

PROG = "palette-recolor"


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog=PROG, description="Recolour every image of a weight stack "
                            "with an edited palette.")
    parser.add_argument("stack", help="weight stack (.npz or .zarr) or splat stack from "
                                      "palette-decompose")
    parser.add_argument("--palette",
                        help='palette JSON: {"palette": ["#rrggbb", ...]}, as many colours as '
                             "the stack's palette: everywhere, or inside the selection given")
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
    where.add_argument("--edits", metavar="FILE",
                       help="replay the local edits saved in FILE (a selection given as well "
                            "stacks on top of them)")
    where.add_argument("--save-edits", metavar="FILE",
                       help="save the local edits (and copies of their masks, in "
                            "FILE-stem.masks/) to replay them with --edits")
    splats = parser.add_argument_group(
        "splat stacks", "a splat stack from palette-decompose SCENE.ply is recoloured into a "
        "splat file: -o SCENE.ply, .compressed.ply, .spz or .splat (docs/splat_files.md)")
    splats.add_argument("--residual", choices=("follow", "keep", "scale"), default="follow",
                        help="the splats' view-dependent colour under an edit: follow the "
                             "edit's local map of colours (default), keep it, or scale it "
                             "with the colour")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _run(build_parser().parse_args(argv)))


def run() -> NoReturn:
    """The console script: ``main``, then the process ends without Python's teardown."""
    exit_without_teardown(main())


def _run(args) -> int:
    from splat_files.stack import is_splat_stack

    if is_splat_stack(args.stack):
        from splat_files.commands import recolor_command

        return recolor_command(args)
    selected = args.mask or args.select_colour is not None or args.select_near
    if args.palette is None and not (args.edits and not selected):
        raise InputError("give --palette (with a selection: the colours inside it), or "
                         "--edits FILE to replay saved edits")
    stack = read_stack(args.stack)
    k = len(stack.palette)
    palette = None if args.palette is None else read_palette_json(args.palette, k=k)
    edits = read_edits(args.edits, stack) if args.edits else []
    if selected:
        selection = Selection(mask=args.mask and Path(args.mask), colour=args.select_colour,
                              near=args.select_near and parse_near(args.select_near),
                              threshold=args.threshold, distance=args.distance,
                              feather=args.feather)
        edits.append(LocalEdit(selection, palette))
        palette = None
    if args.save_edits and not edits:
        raise InputError("--save-edits needs a selection or --edits to save")
    outside = np.asarray(stack.palette, np.float64) if palette is None else palette
    if args.save_edits:  # before any work
        check_edits_writable(Path(args.save_edits), edits, args.force)
    written = recolor_stack(stack, outside, args.output, args.force, args.frames, edits)
    where = f" ({len(edits)} local edit{'s' * (len(edits) > 1)})" if edits else ""
    print(f"wrote {len(written)} recoloured files to {args.output}{where}")
    if args.save_edits:
        write_edits(args.save_edits, stack, edits, args.force)
        print(f"saved the local edits to {args.save_edits}")
    return 0


if __name__ == "__main__":
    run()
