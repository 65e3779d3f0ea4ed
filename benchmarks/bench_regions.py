"""Local edits of a scene: a region edit of the weight NeRF against the simulator's exact
"only this object recoloured".

The built-in ``clay-twins`` has a clay vase and a clay ball of one palette colour but of
two materials (``colour_of``), so the simulator re-traces the ball alone recoloured
(``simulate.with_palette(only=...)``). The run (``nerf-stage train`` defaults, or
``--iters P F``; reused from ``OUT/clay-twins-run``, which ``bench_simulated.py --out OUT``
also writes) renders its test views once with their samples; the clay colour is then
recoloured inside a box around the ball (``WeightRender.with_regions``) and scored against
the re-traced truth: PSNR on the test views, and the mean change outside, over the pixels
the truth leaves unchanged (the vase among them). A global edit of the same colour, scored
against the same truth, shows what the region is for. Timing: a region moved and the view
recoloured, with no network, on a cached view of 100 x 100 (best of 20). Figure: one test
view, truth and render, before and after, with the error map, ``OUT/regions.png``.

    python benchmarks/bench_regions.py [--out benchmarks/out/simulated] [--iters P F]
                                       [--region box:x0,y0,z0,x1,y1,z1]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_nerf import scene_run
from PIL import Image
from results import table, write_result

from nerf_stage.edit.editing import render_poses, render_weights
from nerf_stage.edit.evaluation import resimulated_views
from nerf_stage.edit.regions import parse_region
from nerf_stage.simulation import SimulationRecord
from nerf_stage.train.config import TrainConfig
from nerf_stage.train.metrics import image_scores

SCENE, OBJECT = "clay-twins", "clay ball"
REGION = "box:0.2,-0.1,-0.6,1.6,1.2,0.8"  # around the ball, far from the vase
NEW_CLAY = [0.1, 0.6, 0.55]  # teal
UNCHANGED = 1 / 255  # a truth pixel that moves less than this is outside the edit


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/simulated"))
    parser.add_argument("--iters", type=int, nargs=2, default=None, metavar=("P", "F"))
    parser.add_argument("--region", default=REGION, help=f"the region (default {REGION})")
    args = parser.parse_args()
    region, = parse_region(args.region)
    config = TrainConfig(**dict(zip(("pretrain_iters", "finetune_iters"), args.iters or ())))
    dataset, run, _ = scene_run(SCENE, args.out, config)
    names, poses, cameras = render_poses(run, dataset, "test", None)
    render = render_weights(run, names, poses, {}, False, cameras, samples=True)
    edit = run.palette.copy()
    edit[0] = NEW_CLAY
    simulation = SimulationRecord.from_meta(run.record.stack_meta)
    truth = resimulated_views(simulation, run.palette, poses, render.background)
    truth_local = resimulated_views(simulation, edit, poses, render.background, {OBJECT})
    truth_global = resimulated_views(simulation, edit, poses, render.background)

    before = render.recolor()
    local = render.with_regions([region]).recolor(inside=edit)
    rows = {
        "reconstruction": image_scores(before, truth),
        "region edit": image_scores(local, truth_local),
        "global edit against the global truth": image_scores(render.recolor(edit), truth_global),
        "global edit against the local truth": image_scores(render.recolor(edit), truth_local),
    }
    outside = np.abs(truth_local - truth).max(-1) < UNCHANGED
    leak = float(np.abs(local - before).mean(-1)[outside].mean() * 255)
    samples = len(render.samples.pixel) / render.opacity.size
    seconds = region_seconds(run, poses[0], region)
    made = table(f"{SCENE}: the {OBJECT} recoloured inside {args.region} (test views)",
                 ["render against truth", "PSNR", "SSIM"],
                 [[label, s["psnr"], s["ssim"]] for label, s in rows.items()])
    print(f"\nmean change outside (pixels the truth leaves unchanged, "
          f"{outside.mean():.0%} of all): {leak:.3f} / 255")
    print(f"samples kept per pixel: {samples:.1f}; region moved and a 100 x 100 view "
          f"recoloured: {seconds * 1000:.2f} ms (best of 20, no network)")
    results = {"scores": rows, "outside_change_255": leak, "outside_share": float(outside.mean()),
               "samples_per_pixel": samples, "region_recolour_seconds": seconds,
               "region": region.to_dict(), "edit": edit.tolist()}
    outside_table = table("outside the region, and speed",
                          ["mean change outside (0-255)", "samples kept a pixel",
                           "region moved, view recoloured (ms)"],
                          [[round(leak, 3), round(samples, 1), round(1000 * seconds, 2)]])
    write_result("regions", "Local edits of a scene against the simulator's exact edit",
                 [made, outside_table], results)
    view = [truth[0], before[0], truth_local[0], local[0],
            np.repeat(np.abs(local[0] - truth_local[0]).mean(-1, keepdims=True) * 10, 3, -1)]
    picture = (np.clip(np.concatenate(view, 1), 0, 1) * 255).round().astype(np.uint8)
    image = Image.fromarray(picture)
    image.resize((image.width * 3, image.height * 3), Image.NEAREST).save(args.out / "regions.png")


def region_seconds(run, pose: np.ndarray, region, repeats: int = 20) -> float:
    """Best time to split a cached 100 x 100 view by ``region``, moved, and recolour it."""
    camera = run.intrinsics
    scale = 100 / camera.height
    camera = replace(camera, width=round(camera.width * scale), height=100,
                     fx=camera.fx * scale, fy=camera.fy * scale, cx=camera.cx * scale,
                     cy=camera.cy * scale)
    view = render_weights(run, ["view"], pose[None], {}, False, camera, samples=True)
    edit = 1 - run.palette
    best = np.inf
    for i in range(repeats):
        moved = replace(region, centre=tuple(np.add(region.centre, 0.01 * i)))
        start = time.perf_counter()
        view.with_regions([moved]).recolor(inside=edit)
        best = min(best, time.perf_counter() - start)
    return best


if __name__ == "__main__":
    main()
