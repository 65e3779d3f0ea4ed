"""``palette-decompose``: images -> shared palette + weight stack (NPZ)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from ..decompose import WEIGHT_METHODS, decompose
from ..errors import InputError
from ..io import atomic_outputs, check_writable, save_image
from ..recolor import palette_to_hex, write_palette_json
from ..render import layer_paths, palette_swatch
from ..stack import write_stack
from . import ArgumentParser, run_cli

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
    parser.add_argument("--method", choices=sorted(WEIGHT_METHODS), default="mvc",
                        help="weight method (default mvc)")
    parser.add_argument("--spatial-scale", type=float, default=None, metavar="S",
                        help="rgbxy only: weight of canvas position against colour "
                             "(default 1; X and Y run over [0, S])")
    parser.add_argument("-o", "--output", default="weights.npz",
                        help="weight stack to write (default weights.npz); palette.png and "
                             "palette.json go beside it")
    parser.add_argument("--layers", metavar="DIR", default=None,
                        help="also write one weight-map PNG per palette colour per image here")
    parser.add_argument("--dtype", choices=("float32", "float16"), default="float32",
                        help="storage type of the weights (default float32)")
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _run(build_parser().parse_args(argv)))


def _run(args) -> int:
    if args.k is not None and args.k < 4:
        raise InputError(f"-k must be at least 4, got {args.k}")
    if args.max_error is not None and not args.max_error >= 0:
        raise InputError(f"--max-error must be a non-negative number, got {args.max_error}")
    options = {}
    if args.spatial_scale is not None:
        if args.method != "rgbxy":
            raise InputError("--spatial-scale applies to --method rgbxy only")
        if not 0 < args.spatial_scale < float("inf"):
            raise InputError(f"--spatial-scale must be a positive number, got {args.spatial_scale}")
        options["spatial_scale"] = args.spatial_scale
    k = 6 if args.k is None and args.max_error is None else args.k
    output = Path(args.output)
    if output.suffix != ".npz":
        raise InputError(f"output must end in .npz, got {output}")
    swatch, palette_json = output.parent / "palette.png", output.parent / "palette.json"
    check_writable([output, swatch, palette_json], args.force)
    layers = Path(args.layers) if args.layers else None
    if layers is not None:
        if layers.exists() and (not layers.is_dir() or (any(layers.iterdir()) and not args.force)):
            raise InputError(f"layers folder {layers} exists and is not empty "
                             "(use --force to write into it)")
        check_writable([layers / "probe"], True)

    result = decompose(args.inputs, k, args.max_error, args.method, args.dtype, options)
    stack = result.stack
    n_colours = len(stack.palette)
    if k is not None and n_colours < k and args.max_error is None:
        print(f"{PROG}: note: the palette has {n_colours} colours, fewer than -k {k}: the "
              "convex hull of the colours has no more vertices; using the whole hull",
              file=sys.stderr)

    start = time.perf_counter()
    with atomic_outputs() as stage:
        with open(stage(output), "wb") as f:
            write_stack(stack, f, args.dtype)
        palette_swatch(stack.palette).save(stage(swatch), format="PNG")
        with open(stage(palette_json), "w") as f:
            write_palette_json(f, stack.palette)
        if layers is not None:
            for name, weights in zip(stack.names, stack.weights):
                for j, path in enumerate(layer_paths(layers, name, n_colours)):
                    save_image(stage(path), weights[..., j].astype(np.float32))
    result.timings["write"] = time.perf_counter() - start

    print(f"palette ({n_colours} colours): {' '.join(palette_to_hex(stack.palette))}")
    width = max(len(name) for name in stack.names)
    for name, w in zip(stack.names, stack.weights):
        print(f"  {name:<{width}}  {w.shape[1]}x{w.shape[0]}  RMSE {result.rmse[name]:.3f}")
    print(f"RMSE (0-255, per channel) over {len(stack.names)} images: {result.rmse_overall:.3f}")
    print("time: " + ", ".join(f"{stage} {t:.2f} s" for stage, t in result.timings.items()))
    written = [output, swatch, palette_json] + ([layers] if layers is not None else [])
    print("wrote " + ", ".join(map(str, written)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
