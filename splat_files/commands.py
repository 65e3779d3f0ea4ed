"""The palette commands on splat files: ``palette-decompose scene.ply``, ``palette-recolor``
and ``palette-harmonize`` of a splat stack into a splat file (docs/splat_files.md). The
commands' parsers are ``palette_core``'s and ``harmonize``'s; each hands its arguments here
when its input is a splat file or a splat stack."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from palette_core.errors import InputError
from palette_core.palette_file import palette_to_hex, read_palette_json
from palette_core.selection import LocalEdit, Selection, parse_near

from .formats import read_splat_file, write_splat_file
from .stack import decompose_splats, read_splat_stack, write_splat_stack

#: palette-decompose's options that images have and splat files do not.
IMAGE_ONLY = ("layers", "workers", "scheduler", "resume")


def decompose_command(args, default_output: str, method_options: dict,
                      palette_options: dict) -> int:
    """``palette-decompose SCENE`` for one splat file: its splat stack (``-o``, by default
    SCENE's stem + ``.splats.npz`` here), palette swatch and JSON."""
    given = [f"--{name}" for name in IMAGE_ONLY if getattr(args, name)]
    if given or args.dtype != "float32":
        raise InputError(f"{' and '.join(given) or '--dtype'} are for images, not splat files")
    path = Path(args.inputs[0])
    output = (Path(path.name.split(".")[0] + ".splats.npz") if args.output == default_output
              else Path(args.output))
    start = time.perf_counter()
    fields = read_splat_file(path)
    read = time.perf_counter() - start
    stack = decompose_splats(fields, args.k, args.max_error, args.method, args.palette_method,
                             method_options, palette_options,
                             {"file": path.name, "splats": len(fields), "degree": fields.degree})
    stack.source["timings"]["read"] = read
    written = write_splat_stack(stack, output, args.force)
    rebuilt = stack.weights.astype(np.float64) @ stack.palette
    rmse = 255 * np.sqrt(np.mean((rebuilt - stack.colours()) ** 2))
    print(f"{path}: {len(fields)} splats of degree {fields.degree}")
    print(f"palette ({len(stack.palette)} colours): {' '.join(palette_to_hex(stack.palette))}")
    print(f"RMSE (0-255, per channel) of the splats' colours: {rmse:.3f}")
    print("time: " + ", ".join(f"{k} {v:.2f} s" for k, v in stack.source["timings"].items()))
    print("wrote " + ", ".join(map(str, written)))
    return 0


def recolor_command(args) -> int:
    """``palette-recolor STACK --palette P -o SCENE.ply``: the splat stack recoloured with
    ``P`` (inside the selection only, when one is given) into a splat file."""
    if args.mask or args.feather or args.edits or args.save_edits or args.frames:
        raise InputError("a splat stack is recoloured everywhere or in a colour selection "
                         "(--select-colour, --select-near); masks, feathering and saved edits "
                         "are for images")
    if args.palette is None:
        raise InputError("give --palette: the colours of the edit")
    stack = read_splat_stack(args.stack)
    palette = read_palette_json(args.palette, k=len(stack.palette))
    edits = []
    if args.select_colour is not None or args.select_near:
        selection = Selection(colour=args.select_colour,
                              near=args.select_near and parse_near(args.select_near),
                              threshold=args.threshold, distance=args.distance)
        selection.check(len(stack.palette))
        edits, palette = [LocalEdit(selection, palette)], stack.palette
    fields = stack.recoloured(palette, edits, args.residual)
    path = write_splat_file(fields, args.output, args.force)
    changed = int((fields.sh0 != stack.fields.sh0).any(1).sum())
    print(f"wrote {path}: {changed} of {len(fields)} splats recoloured")
    return 0


def harmonize_command(args) -> int:
    """``palette-harmonize STACK --template T -o SCENE.ply``: the splat stack's palette
    harmonised (its hues weighed by what the splats cover), into a splat file."""
    from harmonize import harmonize_palette
    from harmonize.batch import ALL

    if args.template == ALL or args.render:
        raise InputError("a splat stack is harmonised with one template into one splat file "
                         "(no 'all', no --render)")
    if args.output is None:
        raise InputError("give -o SCENE.ply (or .spz, .splat, .compressed.ply): the "
                         "harmonised splats")
    stack = read_splat_stack(args.stack)
    result = harmonize_palette(stack.palette, stack.shares(), args.template, args.strength)
    path = write_splat_file(stack.recoloured(result.palette), args.output, args.force)
    print(f"{result.fit.template.name}: alpha {result.fit.alpha:.2f} deg, cost "
          f"{result.fit.cost:.1f}\n  palette {' '.join(palette_to_hex(stack.palette))}\n"
          f"       -> {' '.join(palette_to_hex(result.palette))}\n  wrote {path}")
    return 0
