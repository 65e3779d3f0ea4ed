"""``palette-decompose``: images and videos -> shared palette + weight stack (NPZ or Zarr;
``decompose.decompose_to``); a splat file -> its splat stack (``splat_files.commands``)."""

from __future__ import annotations

import sys
from typing import NoReturn

from ..collection import Collection
from ..decompose import Decomposition, decompose_to
from ..errors import InputError
from ..io import DEFAULT_MAX_PIXELS
from ..palette_file import palette_to_hex
from ..palettes import PALETTE_METHODS
from ..stack import DEFAULT_STACK
from ..weights import WEIGHT_METHODS
from . import ArgumentParser, add_method_options, exit_without_teardown, given_options, run_cli

PROG = "palette-decompose"


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(
        prog=PROG,
        description="Extract one palette shared by all images and per-pixel additive weights.",
    )
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="image files and/or folders, or one splat file (.ply, "
                             ".compressed.ply, .spz, .splat, .sog): its splat stack")
    parser.add_argument("-k", type=int, default=None,
                        help="palette size, at least 4 (default 6 without --max-error)")
    parser.add_argument("--max-error", type=float, default=None, metavar="E",
                        help="smallest palette with reconstruction RMSE <= E (0-255 scale); "
                             "with -k, at most K colours")
    parser.add_argument("--palette-method", choices=sorted(PALETTE_METHODS), default="refined",
                        help=f"palette method, one of {', '.join(PALETTE_METHODS)} (default "
                             "refined: the hull's palette fitted to the pixels)")
    add_method_options(parser, PALETTE_METHODS)
    parser.add_argument("--method", choices=sorted(WEIGHT_METHODS), default="mvc",
                        help=f"weight method, one of {', '.join(WEIGHT_METHODS)} (default mvc); "
                             "a Zarr stack takes the per-colour ones")
    add_method_options(parser, WEIGHT_METHODS)
    parser.add_argument("-o", "--output", default=DEFAULT_STACK,
                        help="weight stack to write (default weights.npz); its palette swatch "
                             "and JSON go beside it (weights.palette.png, weights.palette.json)")
    parser.add_argument("--layers", metavar="DIR", default=None,
                        help="also write one weight-map PNG per palette colour per image here")
    parser.add_argument("--dtype", choices=("float32", "float16"), default="float32",
                        help="storage type of the weights (default float32)")
    parser.add_argument("--max-pixels", type=int, default=DEFAULT_MAX_PIXELS, metavar="N",
                        help="refuse images larger than N pixels, from their header, before "
                             f"decoding (default {DEFAULT_MAX_PIXELS})")
    collection = parser.add_argument_group(
        "collections", "with -o NAME.zarr (needed for videos) the images and frames are read "
        "twice, one at a time, into a chunked Zarr stack: memory does not grow with the "
        "collection")
    collection.add_argument("--workers", type=int, default=None, metavar="N",
                            help="run both passes on a local dask cluster of N processes")
    collection.add_argument("--scheduler", default=None, metavar="ADDRESS",
                            help="run both passes on the dask.distributed cluster at ADDRESS "
                                 "(the store must be a path or URL all workers can write)")
    collection.add_argument("--resume", action="store_true",
                            help="finish a store whose second pass was stopped")
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _run(build_parser().parse_args(argv)))


def run() -> NoReturn:
    """The console script: ``main``, then the process ends without Python's teardown."""
    exit_without_teardown(main())


def _run(args) -> int:
    from splat_files import is_splat_file

    if any(is_splat_file(path) for path in args.inputs):
        if len(args.inputs) > 1:
            raise InputError("a splat file is decomposed on its own: give one input")
        from splat_files.commands import decompose_command

        return decompose_command(args, DEFAULT_STACK, given_options(args, WEIGHT_METHODS),
                                 given_options(args, PALETTE_METHODS))
    result, written = decompose_to(
        args.inputs, args.output, args.layers, args.force, args.workers, args.scheduler,
        args.resume, k=args.k, max_error=args.max_error, method=args.method, dtype=args.dtype,
        method_options=given_options(args, WEIGHT_METHODS), palette_method=args.palette_method,
        max_pixels=args.max_pixels, palette_options=given_options(args, PALETTE_METHODS))
    if isinstance(result, Collection):
        _print_collection(result)
    else:
        _print_decomposition(result)
    print("time: " + ", ".join(f"{stage} {t:.2f} s" for stage, t in result.timings.items()))
    print("wrote " + ", ".join(map(str, written)))
    return 0


def _print_decomposition(result: Decomposition) -> None:
    stack = result.stack
    if result.hull_too_small:
        print(f"{PROG}: note: the palette has {len(stack.palette)} colours, fewer than -k "
              f"{result.requested_k}: the convex hull of the colours has no more vertices; "
              "using the whole hull", file=sys.stderr)
    print(f"palette ({len(stack.palette)} colours): {' '.join(palette_to_hex(stack.palette))}")
    width = max(len(name) for name in stack.names)
    for name, w in zip(stack.names, stack.weights):
        print(f"  {name:<{width}}  {w.shape[1]}x{w.shape[0]}  RMSE {result.rmse[name]:.3f}")
    print(f"RMSE (0-255, per channel) over {len(stack.names)} images: {result.rmse_overall:.3f}")


def _print_collection(done: Collection) -> None:
    palette = done.palette.vertices
    print(f"palette ({len(palette)} colours): {' '.join(palette_to_hex(palette))}")
    print(f"{len(done.names)} images and frames, {done.counts.sum() / 1e6:.1f} Mpx, "
          f"{len(done.codes)} distinct colours")


if __name__ == "__main__":
    run()
