"""Splat bakes against the network and the simulator's truth, on the training rig's test views
and on views off it.

For each scene (default the still life and the Cornell box) the run is trained with
``nerf-stage train``'s defaults (or reused from ``OUT/<scene>-run``, which
``bench_simulated.py --out OUT`` also writes), baked (``nerf-stage bake``'s defaults, timed),
and drawn (``splats.render_splats``) at the dataset's test views and at ``--off-ring`` views
away from the rig (``cameras.off_ring_poses``: above it, closer, farther), whose truth the
path tracer renders. Reported per scene: splats, file size, bake seconds, and PSNR of the
network's render, of its diffuse part (``diffuse_render``: the network without its view
dependence, which a splat's one set of weights cannot hold) and of the bake against the
truth, and of the bake against the network, on and off the rig; then, at ``--scale`` times
the training resolution (a browser draws the splats finer still), the PSNR of the network
and of the bake against the truth path traced at that resolution. Figure
``OUT/splats.png``: per scene, truth, network and bake of the first test view and the
error maps of network and bake (4 |render - truth|), then the same of the first off-ring
view (at ``--scale``).

    python benchmarks/bench_splats.py [--out benchmarks/out/simulated] [--scenes ...]
        [--off-ring 6] [--refine-steps N] [--max-splats N] [--scale 4]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_nerf import scene_run
from bench_simulated import figure
from results import table, write_result

from nerf_stage.data.cameras import off_ring_poses
from nerf_stage.edit.editing import WeightRender, render_poses
from nerf_stage.edit.evaluation import composited
from nerf_stage.simulation import BUILTIN_SCENES, load_scene, render_terms
from nerf_stage.splats import MAX_SPLATS, bake_run, render_splats, write_splats
from nerf_stage.train.config import TrainConfig
from nerf_stage.train.metrics import psnr


def truth(scene: str, poses: np.ndarray, resolution: tuple[int, int],
          background: np.ndarray) -> np.ndarray:
    """(N, H, W, 3) the built-in ``scene`` path traced from ``poses`` at its own settings."""
    from nerf_stage.simulation import with_overrides

    spec = load_scene(scene)
    width, height = resolution
    spec = with_overrides(spec, resolution=width if width == height else None)
    radiance, alpha = render_terms(spec, poses, split=False)
    return composited(radiance[..., 0, :], alpha, background)


def diffuse_render(run, poses: np.ndarray, camera, directions: np.ndarray) -> tuple:
    """The network's weight render from ``poses`` with every sample seen from each of the
    unit ``directions`` (D, 3) in turn, averaged: its diffuse part. Returns (N, H, W, M)
    weights and (N, H, W) opacity (which no direction changes)."""
    import torch

    field, colour = run.field, run.field.colour
    total = 0
    try:
        for d in directions:
            fixed = torch.as_tensor(d / np.linalg.norm(d), dtype=torch.float32)
            field.colour = lambda h, _, fixed=fixed: colour(h, fixed.to(h).expand(len(h), 3))
            weights, opacity = run.render(poses, False, camera)
            total = total + weights
    finally:
        field.colour = colour
    return total / len(directions), opacity


def mean_psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean([psnr(x, y) for x, y in zip(a, b)]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/simulated"))
    parser.add_argument("--scenes", nargs="+", default=["still-life", "cornell-box"],
                        choices=BUILTIN_SCENES)
    parser.add_argument("--off-ring", type=int, default=6)
    parser.add_argument("--refine-steps", type=int, help="default: the device's "
                        "(nerf_stage.splats.REFINE_STEPS)")
    parser.add_argument("--max-splats", type=int, default=MAX_SPLATS)
    parser.add_argument("--scale", type=int, default=4,
                        help="also score the views at this many times the training "
                             "resolution, as a browser draws them (1: not)")
    args = parser.parse_args()
    results, rows, pictures = {}, [], []
    for scene in args.scenes:
        dataset, run, _ = scene_run(scene, args.out, TrainConfig(backbone="grid"))
        start = time.perf_counter()
        splats = bake_run(args.out / f"{scene}-run", args.max_splats, args.refine_steps,
                          run=run)
        seconds = time.perf_counter() - start
        with tempfile.TemporaryDirectory() as folder:
            write_splats(splats, Path(folder) / "s.npz")
            megabytes = (Path(folder) / "s.npz").stat().st_size / 2**20
        background = np.asarray(run.config.background, np.float64)
        names, poses, cameras = render_poses(run, dataset, "test", None)
        cam = load_scene(scene).camera
        away = off_ring_poses(cam.rig, args.off_ring, cam.target, cam.radius, cam.elevation,
                              cam.arc)
        views = {"ring": (poses, dataset.images[dataset.indices("test")]),
                 "off ring": (away, truth(scene, away, (cam.width, cam.height), background))}
        scores = {"splats": len(splats), "megabytes": megabytes, "bake_seconds": seconds}
        picture = []
        directions = -dataset.poses[dataset.indices("train")][::12, :3, 2]  # 9 of 100
        big = cameras[0].upscaled(args.scale)
        for label, (where, real) in views.items():
            network = _recoloured(run, *run.render(where, False, cameras[0]), background)
            diffuse = _recoloured(run, *diffuse_render(run, where, cameras[0], directions),
                                  background)
            baked = _recoloured(run, *render_splats(splats, where, cameras[0]), background)
            scores[label] = {"network": mean_psnr(network, real),
                             "network_diffuse": mean_psnr(diffuse, real),
                             "bake": mean_psnr(baked, real),
                             "bake_vs_network": mean_psnr(baked, network)}
            if args.scale > 1:  # the truth path traced at the finer resolution
                real = truth(scene, where, (big.width, big.height), background)
                network = _recoloured(run, *run.render(where, False, big), background)
                baked = _recoloured(run, *render_splats(splats, where, big), background)
                scores[label]["scaled"] = {"network": mean_psnr(network, real),
                                           "bake": mean_psnr(baked, real)}
            picture += [real[0], network[0], baked[0],  # then the error maps, 4 |x - truth|
                        *(np.clip(4 * np.abs(x[0] - real[0]), 0, 1) for x in (network, baked))]
        results[scene] = scores
        rows.append([scene, len(splats), megabytes, seconds,
                     *[scores[v][k] for v in views for k in ("network", "network_diffuse",
                                                            "bake", "bake_vs_network")],
                     *[scores[v].get("scaled", {}).get(k) for v in views
                       for k in ("network", "bake")]])
        pictures.append(picture)
        print(f"{scene}: {rows[-1]}", flush=True)
    made = table("Splat bakes (PSNR dB against the truth, and of the bake against the network)",
                 ["scene", "splats", "MB", "bake s", "ring: network", "ring: network diffuse",
                  "ring: bake", "ring: bake vs network", "off ring: network",
                  "off ring: network diffuse", "off ring: bake", "off ring: bake vs network",
                  *[f"{v} x{args.scale}: {k}" for v in views for k in ("network", "bake")]],
                 rows)
    write_result("splats", "Splat bakes against the network and the truth", [made], results)
    figure(pictures, args.out / "splats.png")


def _recoloured(run, weights, opacity, background) -> np.ndarray:
    return WeightRender(weights, opacity, [], run.palette, run.basis, run.order, background,
                        {}).recolor()


if __name__ == "__main__":
    main()
