"""``palette-decompose``: images -> shared palette + weight stack (NPZ)."""

from __future__ import annotations

import sys
from typing import NoReturn

from ..cluster import check_workers, dask_client
from ..collection import decompose_collection
from ..decompose import decompose
from ..errors import InputError
from ..io import DEFAULT_MAX_PIXELS
from ..palette_file import palette_paths, palette_to_hex
from ..palettes import PALETTE_METHODS
from ..sources import is_video
from ..stack import DEFAULT_STACK, is_zarr
from ..weights import WEIGHT_METHODS
from . import ArgumentParser, add_method_options, exit_without_teardown, given_options, run_cli

PROG = "palette-decompose"


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(
        prog=PROG,
        description="Extract one palette shared by all images and per-pixel additive weights.",
    )
    parser.add_argument("inputs", nargs="+", metavar="INPUT", help="image files and/or folders")
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
    check_workers(args.workers, args.scheduler)
    if is_zarr(args.output) or any(is_video(path) for path in args.inputs):
        return _run_collection(args)
    if args.workers is not None or args.scheduler is not None or args.resume:
        raise InputError("--workers, --scheduler and --resume need -o NAME.zarr")
    result = decompose(args.inputs, args.k, args.max_error, args.method, args.dtype,
                       given_options(args, WEIGHT_METHODS), args.palette_method, args.max_pixels,
                       given_options(args, PALETTE_METHODS))
    written = result.write(args.output, args.layers, args.force)
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
    print("time: " + ", ".join(f"{stage} {t:.2f} s" for stage, t in result.timings.items()))
    print("wrote " + ", ".join(map(str, written)))
    return 0


def _run_collection(args) -> int:
    if not is_zarr(args.output):
        raise InputError(f"videos are decomposed into a Zarr stack: give -o NAME.zarr, not "
                         f"{args.output}")
    if args.layers:
        raise InputError("--layers needs -o NAME.npz: a Zarr stack is written without them")
    with dask_client(args.workers, args.scheduler) as client:
        done = decompose_collection(args.inputs, args.output, args.k, args.max_error,
                                    args.palette_method, args.dtype, args.max_pixels, client,
                                    args.resume, args.force, method=args.method,
                                    method_options=given_options(args, WEIGHT_METHODS),
                                    palette_options=given_options(args, PALETTE_METHODS))
    palette = done.palette.vertices
    megapixels = done.counts.sum() / 1e6
    print(f"palette ({len(palette)} colours): {' '.join(palette_to_hex(palette))}")
    print(f"{len(done.names)} images and frames, {megapixels:.1f} Mpx, "
          f"{len(done.codes)} distinct colours")
    print("time: " + ", ".join(f"{stage} {t:.2f} s" for stage, t in done.timings.items()))
    print("wrote " + ", ".join(map(str, [args.output, *palette_paths(args.output)])))
    return 0


if __name__ == "__main__":
    run()
