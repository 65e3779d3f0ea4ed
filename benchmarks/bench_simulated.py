"""Every built-in simulated scene at the default training settings: the defaults are chosen
on all of them, not on one.

The scenes differ in camera rig (orbit, hemisphere, front arcs of 50 and 140 degrees, a
narrow forward-facing arc), in what ends within view (a closed box, a floor and walls that
stop, a field that reaches far beyond the cameras, a wall that fills every view), in
object size (marbles a few pixels across) and in transport order (direct light, orders 1,
2 and 3). Each is simulated once (``nerf-stage simulate``; a scene without editable
materials is decomposed, ``palette-decompose -k 6``), trained with ``nerf-stage train``'s
defaults (or ``--iters P F``) and scored on its test views: PSNR and SSIM through the
weights, the global edit (every palette colour takes the next one's) against the scene
re-simulated with it, and, for every editable material, the edit of that material alone
(its colour inverted) against the exact truth from the simulator's weights of the test
views (``metrics.edit_response``): 1 when the render moves as the truth does where the
material is seen, 0 when the material went to another channel. A response below
``LOST`` fails, however high the PSNR. One test view per scene, truth and render, before
and after the global edit: ``OUT/simulated.png``.

    python benchmarks/bench_simulated.py [--out benchmarks/out/simulated] [--scenes ...]
                                         [--iters P F] [--backbone splats] [--minutes M]
                                         [--curve-points N]

``--backbone`` trains another backbone than the default (runs kept apart by name);
``--minutes`` limits each run's training time, to compare backbones at one budget;
``--curve-points N`` keeps about N checkpoints of each run it trains and scores them on the
test views (``curve`` in the results: training seconds and test PSNR).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_nerf import scene_run
from bench_scenes import checkpoint_curve
from PIL import Image
from results import table, write_result

from nerf_stage.backbones import BACKBONES
from nerf_stage.edit.editing import WeightRender, render_poses
from nerf_stage.edit.evaluation import composited, evaluate, rolled_palette
from nerf_stage.simulation import BUILTIN_SCENES
from nerf_stage.train.config import TrainConfig
from nerf_stage.train.metrics import edit_response
from palette_core.basis import Basis, weights_to_rgb
from palette_core.stack import read_stack

LOST = 0.5  # an edit response below this: the material is lost to other channels


def truth_views(stack, names, alpha, palette, background) -> np.ndarray:
    """(N, H, W, 3) the simulator's views ``names`` (alpha (N, H, W)) recoloured with
    ``palette`` through their exact transport weights, composited like the dataset's PNGs."""
    weights = np.stack([np.asarray(stack.weights[stack.names.index(n)], np.float64)
                        for n in names])
    return composited(weights_to_rgb(weights, palette, Basis.TRANSPORT, stack.order), alpha,
                      background)


def test_render(run, dataset) -> WeightRender:
    """The run's weights rendered at the dataset's test views."""
    names, poses, cameras = render_poses(run, dataset, "test", None)
    values, opacity = run.render(poses, False, cameras)
    return WeightRender(values, opacity, names, run.palette, run.basis, run.order,
                        np.asarray(run.config.background, np.float64), {})


def material_edits(render: WeightRender, dataset, stack) -> list[dict]:
    """Per editable material: its colour inverted alone, the test ``render``'s response to it
    (``metrics.edit_response``) and the share of test pixels where it shows."""
    test = dataset.indices("test")
    frames, alpha = [dataset.names[i] for i in test], dataset.alpha[test]
    before = render.recolor()
    truth_before = truth_views(stack, frames, alpha, render.palette, render.background)
    rows = []
    for k in range(len(render.palette)):
        edit = render.palette.copy()
        edit[k] = 1 - edit[k]
        response, seen = edit_response(
            before, render.recolor(edit), truth_before,
            truth_views(stack, frames, alpha, edit, render.background))
        rows.append({"material": k, "response": response, "seen": seen})
    return rows


def figure(rows: list, path: Path, height: int = 200) -> None:
    """One test view a scene: truth, render, truth edited, render edited; each scene's row
    scaled to ``height`` pixels (nearest), rows padded white to the widest."""
    strips = []
    for row in rows:
        strip = Image.fromarray((np.clip(np.concatenate(row, 1), 0, 1) * 255).round()
                                .astype(np.uint8))
        width = round(strip.width * height / strip.height)
        strips.append(np.asarray(strip.resize((width, height), Image.NEAREST)))
    widest = max(strip.shape[1] for strip in strips)
    Image.fromarray(np.concatenate([np.pad(strip, ((0, 0), (0, widest - strip.shape[1]), (0, 0)),
                                           constant_values=255) for strip in strips])).save(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/simulated"))
    parser.add_argument("--scenes", nargs="+", default=list(BUILTIN_SCENES),
                        choices=BUILTIN_SCENES)
    parser.add_argument("--iters", type=int, nargs=2, default=None, metavar=("P", "F"))
    parser.add_argument("--backbone", default="grid", choices=list(BACKBONES))
    parser.add_argument("--minutes", type=float, default=0.0,
                        help="training time limit of each run (0: none)")
    parser.add_argument("--curve-points", type=int, default=0,
                        help="checkpoints of each new run scored on the test views for the "
                             "PSNR-against-time curve (0: the end alone)")
    args = parser.parse_args()
    iters = dict(zip(("pretrain_iters", "finetune_iters"), args.iters or ()))
    config = TrainConfig(backbone=args.backbone, minutes=args.minutes, **iters)
    if args.curve_points:
        config = replace(config, checkpoint_every=max(1, config.total_iters // args.curve_points))
    name = "" if args.backbone == "grid" else f"-{args.backbone}"
    results, rows, pictures = {}, [], []
    for scene in args.scenes:
        snapshots = args.out / f"{scene}{name}-snapshots" if args.curve_points else None
        dataset, run, stack_path = scene_run(scene, args.out, config, snapshots)
        stack = read_stack(stack_path)
        scores = evaluate(run, dataset, progress=False)
        scores["seconds"] = run.record.log[-1]["seconds"]
        scores["unbounded"] = run.box.unbounded
        render = test_render(run, dataset)
        materials = material_edits(render, dataset, stack) if run.basis == Basis.TRANSPORT else []
        scores["materials"] = materials
        if snapshots:
            scores["curve"] = checkpoint_curve(snapshots, dataset, dataset.indices("test"))
        results[scene] = scores
        edit = scores.get("edit", {})
        lost = [m["material"] for m in materials if not m["response"] >= LOST]
        rows.append([scene, "unbounded" if run.box.unbounded else "box",
                     scores["reconstruction"]["psnr"], scores["reconstruction"]["ssim"],
                     edit.get("psnr", float("nan")),
                     " ".join(f"{m['response']:.2f}" for m in materials) or "-",
                     ", ".join(map(str, lost)) or "none", scores["seconds"]])
        pictures.append(_view_row(render, dataset, stack))
        print(f"{scene}: {rows[-1]}", flush=True)
    made = table(f"Built-in scenes at {'the default budget' if not iters else args.iters} "
                 "(test views)",
                 ["scene", "space", "PSNR", "SSIM", "edit PSNR", "edit response per material",
                  f"lost (< {LOST})", "train s"], rows)
    write_result(f"simulated{name}", "Simulated scenes at the defaults", [made], results)
    figure(pictures, args.out / f"simulated{name}.png")


def _view_row(render: WeightRender, dataset, stack) -> list:
    """Truth and render of the first test view, then both with the global edit (the truth
    from the simulator's weights; a scene without editable materials shows its render
    recoloured only)."""
    first = dataset.indices("test")[:1]
    edit = rolled_palette(render.palette)
    truth = dataset.images[first[0]]
    edited_truth = (truth_views(stack, [dataset.names[first[0]]], dataset.alpha[first], edit,
                                render.background)[0]
                    if stack.basis == Basis.TRANSPORT else truth)
    return [truth, render.recolor()[0], edited_truth, render.recolor(edit)[0]]


if __name__ == "__main__":
    main()
