"""Local edits in photos: the time of a selection recolour of one megapixel, in the library.

A photo is decomposed (``palette-decompose -k 6``), its weights resized to 1000 x 1000
(bilinear, so the recolour sees the photo's weights at one megapixel) and recoloured with
every palette colour inverted: everywhere (``basis.weights_to_rgb``), and inside a hard
mask, a feathered mask, a palette-colour selection, a near-colour selection and two
edits stacked (the hard mask under the palette-colour selection; ``selection.recolor_local``).
Best of ``--repeats`` runs each; the selection's own values are part of the time. Also
checks that outside a hard mask the recolour equals the unedited reconstruction exactly.

The figure (``--figure``, default ``benchmarks/out/selection.png``) shows the photo at its
own size: as decomposed, the central box's most used strong colour (weight times chroma)
recoloured teal
everywhere, the same edit inside that box only (feathered by 8 pixels), and the box.

    python benchmarks/bench_selection.py [--photo examples/photos/coffee.jpg] [--repeats 7]
                                         [--figure benchmarks/out/selection.png]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image
from results import table, write_result
from scipy.ndimage import zoom

from palette_core import decompose
from palette_core.basis import weights_to_rgb
from palette_core.selection import LocalEdit, Selection, recolor_local

SIZE = 1000


def figure(weights: np.ndarray, palette: np.ndarray, path: Path) -> None:
    """Original, a colour edited everywhere, the same edit inside the central box only, and
    the box, side by side (module docstring)."""
    h, w = weights.shape[:2]
    box = np.zeros((h, w), np.uint8)
    box[h // 4: 3 * h // 4, w // 4: 3 * w // 4] = 255
    chroma = np.ptp(palette, axis=1)
    k = int(np.argmax(weights[box > 0].sum(0) * chroma))  # the box's most used strong colour
    edited = palette.copy()
    edited[k] = [0.1, 0.6, 0.55]
    with tempfile.TemporaryDirectory() as folder:
        Image.fromarray(box).save(Path(folder) / "box.png")
        local = recolor_local(weights, palette, [
            LocalEdit(Selection(mask=Path(folder) / "box.png", feather=8.0), edited)], "photo",
            "additive")
    panels = [weights_to_rgb(weights, palette), weights_to_rgb(weights, edited), local,
              np.repeat(box[..., None] / 255.0, 3, -1)]
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.clip(np.concatenate(panels, 1), 0, 1) * 255).round().astype(np.uint8)
                    ).save(path)


def best_seconds(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--photo", type=Path, default=Path("examples/photos/coffee.jpg"))
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--figure", type=Path, default=Path("benchmarks/out/selection.png"))
    args = parser.parse_args()
    result = decompose([args.photo], k=6)
    figure(np.asarray(result.stack.weights[0], np.float64),
           np.asarray(result.stack.palette, np.float64), args.figure)
    stack_weights = np.asarray(result.stack.weights[0], np.float64)
    h, w = stack_weights.shape[:2]
    weights = zoom(stack_weights, (SIZE / h, SIZE / w, 1), order=1)
    weights /= weights.sum(-1, keepdims=True)
    palette = np.asarray(result.stack.palette, np.float64)
    edited = 1 - palette
    original = weights_to_rgb(weights, palette)
    with tempfile.TemporaryDirectory() as folder:
        inside = np.zeros((SIZE, SIZE), np.uint8)
        inside[250:750, 250:750] = 255
        mask = Path(folder) / "mask.png"
        Image.fromarray(inside).save(mask)
        selections = {
            "hard mask (500 x 500 square)": Selection(mask=mask),
            "feathered mask (8 pixels)": Selection(mask=mask, feather=8.0),
            "palette colour 0 (weight >= 0.5)": Selection(colour=0),
            "near a colour (0.1)": Selection(near=tuple(original[500, 500]), distance=0.1),
        }
        edits = {label: [LocalEdit(s, edited)] for label, s in selections.items()}
        edits["two stacked: hard mask, then palette colour 0"] = [
            LocalEdit(selections["hard mask (500 x 500 square)"], edited),
            LocalEdit(selections["palette colour 0 (weight >= 0.5)"], palette[::-1])]
        hard = recolor_local(weights, palette, next(iter(edits.values())), "photo",
                             result.stack.basis)
        outside = inside == 0
        exact = np.array_equal(hard[outside], original[outside])
        print(f"{args.photo.name} at {SIZE} x {SIZE} ({weights.shape[-1]} weights a pixel); "
              f"outside the hard mask equal to the unedited reconstruction: {exact}")
        times = {"everywhere (weights_to_rgb)": best_seconds(
            lambda: weights_to_rgb(weights, edited), args.repeats)}
        for label, layers in edits.items():
            times[label] = best_seconds(lambda e=layers: recolor_local(
                weights, palette, e, "photo", result.stack.basis), args.repeats)
    made = table(f"{args.photo.name} at {SIZE} x {SIZE}, K = {weights.shape[-1]}",
                 ["recolour", f"best of {args.repeats} (ms)"],
                 [[label, round(1000 * seconds, 1)] for label, seconds in times.items()])
    write_result("selection", "Local edits in photos: a megapixel recoloured", [made],
                 {"seconds": times, "outside_hard_mask_exact": exact})


if __name__ == "__main__":
    main()
