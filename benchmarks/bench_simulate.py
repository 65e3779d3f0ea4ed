"""Light-transport orders on the Cornell box, and the simulation time targets.

1. Orders 0..3 against a deep reference (every path up to the same depth, nothing
   dropped): the energy each order leaves out (RMSE on the 0-255 scale of the
   clipped images, and the share of the reference's total radiance), the time,
   and the size of the weight stack for the scene's 130 views. Every path has its
   own random stream, so an order's image differs from the reference only by the
   paths it drops.
2. A recolouring check: one view recoloured through the weights of each order
   beside a fresh render of the edited scene (saved as a figure).
3. The targets: the built-in scenes at their default settings (views, resolution,
   samples), timed end to end, with their noise: the RMS difference of two renders
   with different seeds over sqrt(2), relative to the mean of the covered pixels.

    python benchmarks/bench_simulate.py [--out benchmarks/out] [--views 8] [--depth 8]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from results import table, write_result

from nerf_stage.simulation import (
    load_scene,
    render_terms,
    simulate,
    view_poses,
    with_overrides,
    with_palette,
)
from palette_core.basis import Basis, weights_to_rgb

EDITED = np.array([[0.1, 0.45, 0.2],  # red wall -> green
                   [0.7, 0.1, 0.1],  # green wall -> red
                   [0.85, 0.5, 0.1],  # tall box -> orange
                   [0.45, 0.2, 0.7]])  # sphere -> purple
TARGET_SECONDS = {"cornell-box": 180, "still-life": 120}


def rgb(scene, poses) -> np.ndarray:
    """(N, H, W, 3) radiance with the albedos multiplied in."""
    return render_terms(scene, poses, split=False)[0][..., 0, :]


def noise(scene, n_views: int) -> float:
    """Relative RMS noise of one render: two seeds, covered pixels, clipped images."""
    renders = [simulate(with_overrides(scene, views=[n_views, 0, 0], seed=seed), progress=False)
               for seed in (1, 2)]
    covered = (renders[0].alpha > 0) | (renders[1].alpha > 0)
    a, b = (np.clip(r.radiance, 0, 1)[covered] for r in renders)
    return float(np.sqrt(np.mean((a - b) ** 2) / 2) / np.mean((a + b) / 2))


def orders_table(n_views: int, depth: int, out: Path) -> dict:
    base = with_overrides(load_scene("cornell-box"), views=[n_views, 0, 0], max_depth=depth)
    n_full = sum(load_scene("cornell-box").camera.views.values())  # for the stack size
    _, poses = view_poses(base)
    reference = rgb(with_overrides(base, order=depth), poses)
    edited_truth = rgb(with_overrides(with_palette(base, EDITED), order=depth), poses)
    ref_clipped = np.clip(reference, 0, 1)
    recoloured, rows = {}, []
    for order in (0, 1, 2, 3):
        scene = with_overrides(base, order=order)
        start = time.perf_counter()
        sim = simulate(scene, progress=False)
        seconds = time.perf_counter() - start
        m = sim.weights.shape[-1]
        stack_mb = n_full * base.camera.width * base.camera.height * m * 4 / 1e6
        rmse = 255 * np.sqrt(np.mean((np.clip(sim.radiance, 0, 1) - ref_clipped) ** 2))
        left_out = 1 - sim.radiance.sum() / reference.sum()
        recoloured[order] = weights_to_rgb(sim.weights, EDITED, Basis.TRANSPORT, order)
        edit_rmse = 255 * np.sqrt(np.mean((np.clip(recoloured[order], 0, 1)
                                           - np.clip(edited_truth, 0, 1)) ** 2))
        rows.append([order, m, round(seconds, 2), round(stack_mb, 1), round(rmse, 2),
                     f"{100 * left_out:.2f} %", round(edit_rmse, 2)])
    save_figure(reference[0], edited_truth[0], {o: r[0] for o, r in recoloured.items()}, out)
    return table(f"Cornell box: orders against a reference keeping every path ({n_views} views "
                 f"of {base.camera.width}x{base.camera.height}, {base.render.spp} spp, up to "
                 f"{depth} surface vertices; stack size for the dataset's {n_full} views)",
                 ["order", "terms", "seconds", "stack MB", "RMSE (0-255)", "energy left out",
                  "edit RMSE"], rows)


def save_figure(original, truth, recoloured: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("original", original), ("edited, re-simulated", truth)]
    panels += [(f"recoloured, order {o}", image) for o, image in recoloured.items()]
    fig, axes = plt.subplots(1, len(panels), figsize=(2.6 * len(panels), 2.9))
    for ax, (title, image) in zip(axes, panels):
        ax.imshow(np.clip(image, 0, 1), interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "simulate_orders.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"saved {path}")


def targets_table() -> dict:
    rows = []
    for name, limit in TARGET_SECONDS.items():
        scene = load_scene(name)
        start = time.perf_counter()
        simulate(scene, progress=False)
        seconds = time.perf_counter() - start
        cam, render = scene.camera, scene.render
        light = render.light + (f", n={render.order}" if render.light == "indirect" else "")
        rows.append([name, sum(cam.views.values()), f"{cam.width}x{cam.height}", render.spp,
                     light, round(seconds, 1), f"< {limit}", f"{100 * noise(scene, 8):.1f} %"])
    return table("The built-in scenes at their defaults, simulated end to end",
                 ["scene", "views", "size", "spp", "light", "seconds", "target", "noise"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out"))
    parser.add_argument("--views", type=int, default=8, help="views for the order table")
    parser.add_argument("--depth", type=int, default=8, help="surface vertices per path")
    args = parser.parse_args()
    simulate(with_overrides(load_scene("cornell-box"), resolution=4, spp=1, views=[1, 0, 0]),
             progress=False)  # compile the kernels outside the timings
    tables = [orders_table(args.views, args.depth, args.out), targets_table()]
    write_result("simulate", "Simulation: light-transport orders and times", tables, {})


if __name__ == "__main__":
    main()
