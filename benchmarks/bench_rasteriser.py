"""The CPU splat rasteriser: a training step of the splats backbone through numba (the tile
kernels of ``splats/tiles.py``, the projection, covariances and spherical harmonics' values
of ``projection.py``, ``model.py`` and ``sh.py``) against PyTorch throughout (pairs, and
PyTorch's per-splat products: the CPU's path before the kernels, and CUDA's), in one run,
with the pairs a step draws, the pairs a second and the share of a roofline.

A step is what ``splats.backbone._loss`` and ``SplatSteps.update`` do in the RGB stage:
the splats' covariances and their colours in spherical harmonics of degree 3 seen from the
camera, a draw of the view (cut off at the default reach), 0.8 L1 + 0.2 (1 - SSIM) against
an image, the backward and an Adam step. The splats are ``--splats`` random ones in front
of a ``--size`` camera (centres at depths 2 to 6 across the view, log-normal scales whose
median projects to about ``--radius`` pixels, opacities uniform), or a trained run's
(``--run``: its geometry, random colours) seen from its first training camera. Each mode
runs in a fresh process (its peak resident memory is the process's), ``--steps`` steps
after two of warm-up, the median's time reported, and the draw's forward and backward
apart.

Pairs: the (pixel, splat) pairs the step blends (alpha at least 1/255, light left at
least 1e-4). The roofline: each pair costs about ``OPS_PER_PAIR`` floating-point operations
forward and backward (the Gaussian, its exponential counted as ``EXP_OPS``, the blend of 3
colours, the gradients of 6 projection terms and 3 colours), against the machine's peak of
scalar fused multiply-adds on every core (``peak_flops``: independent chains, numba, the
same code generation as the kernels).

    python benchmarks/bench_rasteriser.py [--splats 100000] [--size 504x378] [--steps 5]
        [--run RUN] [--radius 3]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from results import table, write_result

NAMES = {"pairs": "PyTorch: pairs, per-splat products", "tiles": "numba: tiles, per-splat kernels"}
EXP_OPS = 20  # an exponential as floating-point operations (a polynomial and a scaling)
#: forward: box test and offsets 6, the quadratic form 8, the exponential, alpha 2, the
#: blend of 3 values and the opacity 9, the light 2; backward: the same again (alpha is
#: made again), the light 2, q and the colours' gradients 12, alpha's gradient 4, the six
#: projection terms 16
OPS_PER_PAIR = (6 + 8 + EXP_OPS + 2 + 9 + 2) * 2 + 2 + 12 + 4 + 16


def scene(splats: int, width: int, height: int, radius: float, seed: int = 0):
    """Random splats in front of an identity camera (looking down -z): the tensors of a
    ``SplatModel`` of degree 3 and the camera."""
    import torch

    from nerf_stage.data.cameras import Intrinsics

    g = torch.Generator().manual_seed(seed)
    focal = 0.8 * width
    depth = 2 + 4 * torch.rand(splats, generator=g)
    x = (torch.rand(splats, generator=g) - 0.5) * width / focal * depth * 1.1
    y = (torch.rand(splats, generator=g) - 0.5) * height / focal * depth * 1.1
    means = torch.stack([x, y, -depth], 1)
    scale = radius * depth / focal  # a standard deviation of ``radius`` pixels
    scales = torch.log(scale[:, None] * torch.exp(0.5 * torch.randn(splats, 3, generator=g)))
    tensors = {"means": means, "scales": scales, "quats": torch.randn(splats, 4, generator=g),
               "opacities": torch.logit(0.05 + 0.9 * torch.rand(splats, generator=g)),
               "colours": torch.randn(splats, 3, generator=g) * 0.5,
               "colours_rest": torch.randn(splats, 15, 3, generator=g) * 0.05}
    camera = Intrinsics(width=width, height=height, fx=focal, fy=focal, cx=width / 2,
                        cy=height / 2)
    return tensors, camera, torch.eye(4)


def trained_scene(run_dir: str):
    """A trained splat run's geometry with random colours, its first training camera and
    pose."""
    import torch

    from nerf_stage.splats.run import GEOMETRY
    from nerf_stage.train.loading import load_run

    run = load_run(run_dir)
    dataset = run.dataset()
    view = dataset.indices("train")[0]
    pose = torch.as_tensor(dataset.poses[view], dtype=torch.float32)
    pose[:3, 3] = (pose[:3, 3] - torch.as_tensor(run.box.centre)) / run.box.scale
    tensors = {name: getattr(run.model, name).detach().clone() for name in GEOMETRY}
    g = torch.Generator().manual_seed(0)  # colours of degree 3 (a palette-stage run has none)
    tensors["colours"] = torch.randn(len(tensors["means"]), 3, generator=g) * 0.5
    tensors["colours_rest"] = torch.randn(len(tensors["means"]), 15, 3, generator=g) * 0.05
    return tensors, dataset.camera(view), pose


def measure(mode: str, args) -> dict:
    """Time ``args.steps`` training steps with the rasteriser in ``mode`` (this process)."""
    import torch

    from nerf_stage.backbone_settings import SplatConfig
    from nerf_stage.fields.base import RGB
    from nerf_stage.splats import rasterise
    from nerf_stage.splats.run import SplatModel
    from nerf_stage.train.losses import ssim_loss

    rasterise.TILED = mode == "tiles"
    if mode == "pairs":
        pytorch_throughout()
    width, height = map(int, args.size.split("x"))
    tensors, camera, pose = (trained_scene(args.run) if args.run else
                             scene(args.splats, width, height, args.radius))
    model = SplatModel(tensors, RGB, 3)
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-3, eps=1e-15)
    truth = torch.rand(camera.height, camera.width, 3, generator=torch.Generator().manual_seed(1))
    reach = SplatConfig().reach
    times, draws, backwards = [], [], []
    for step in range(args.steps + 2):
        start = time.perf_counter()
        covariance, opacity = model.gaussians()
        values = model.values(pose[:3, 3], 3)
        begin = time.perf_counter()
        drawn, acc = rasterise.draw(model.means, covariance, values, opacity, pose, camera,
                                    reach, {})
        drawn_at = time.perf_counter()
        rgb = (drawn + (1 - acc[:, None])).view(camera.height, camera.width, 3)
        loss = 0.8 * torch.mean(torch.abs(rgb - truth)) + 0.2 * ssim_loss(rgb, truth)
        optimiser.zero_grad(set_to_none=True)
        backward_at = time.perf_counter()
        loss.backward()
        backward_end = time.perf_counter()
        optimiser.step()
        if step >= 2:
            times.append(time.perf_counter() - start)
            draws.append(drawn_at - begin)
            backwards.append(backward_end - backward_at)
    with torch.no_grad():
        pairs = count_pairs(model, pose, camera, reach)
    return {"mode": mode, "splats": len(model.means), "size": f"{camera.width}x{camera.height}",
            "step_s": float(np.median(times)), "draw_s": float(np.median(draws)),
            "backward_s": float(np.median(backwards)), "pairs": pairs,
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "threads": torch.get_num_threads()}


def pytorch_throughout() -> None:
    """The per-splat steps in PyTorch on a CPU too, as on CUDA: the projection, the
    covariances and the spherical harmonics' values."""
    import torch

    from nerf_stage.splats import model, projection, sh

    def torch_covariances(quaternions, scales):
        rotation = model.rotation_matrices(quaternions)
        return (rotation * scales[:, None, :] ** 2) @ rotation.transpose(1, 2)

    projection._CpuProjection.apply = projection._projected
    model._CpuCovariances.apply = torch_covariances
    sh._CpuContraction.apply = lambda basis, coefficients: torch.einsum(
        "sb,sbc->sc", basis, coefficients[:, :basis.shape[1]])


def count_pairs(model, pose, camera, reach) -> int:
    """The pairs a draw of the view blends (the PyTorch path's kept pairs)."""
    from nerf_stage.splats.pairs import pairs

    covariance, opacity = model.gaussians()
    found = pairs(model.means, covariance, opacity, pose, camera, reach, None,
                  (0, 0, camera.width, camera.height))
    return 0 if found is None else int(sum(found[-1]))


def peak_flops(seconds: float = 1.0) -> float:
    """Floating-point operations a second of scalar fused multiply-adds on every core:
    eight independent chains a thread, in numba (the kernels' code generation)."""
    import numba
    from numba import njit, prange

    @njit(parallel=True, fastmath=False)
    def chains(n, out):
        for t in prange(out.shape[0]):
            a = np.full(8, 1.0 + t * 1e-9)
            b, c = 0.999999, 1e-7
            for _ in range(n):
                for k in range(8):
                    a[k] = a[k] * b + c
            out[t] = a.sum()

    threads = numba.get_num_threads()
    out = np.zeros(threads)
    chains(10, out)
    n = 1000
    while True:
        start = time.perf_counter()
        chains(n, out)
        elapsed = time.perf_counter() - start
        if elapsed > seconds:
            return 2 * 8 * n * threads / elapsed
        n *= 4


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--splats", type=int, default=100_000)
    parser.add_argument("--size", default="504x378", help="WIDTHxHEIGHT of the view")
    parser.add_argument("--radius", type=float, default=3.0,
                        help="median projected standard deviation of a splat, in pixels")
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--run", help="a trained splat run instead of random splats")
    parser.add_argument("--mode", choices=("tiles", "pairs"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.mode:  # a child: one mode, its numbers as JSON
        print(json.dumps(measure(args.mode, args)))
        return
    rows = {}
    for mode in ("pairs", "tiles"):
        child = subprocess.run([sys.executable, __file__, *sys.argv[1:], "--mode", mode],
                               capture_output=True, text=True, check=True)
        rows[mode] = json.loads(child.stdout.strip().splitlines()[-1])
        print(mode, rows[mode], flush=True)
    peak = peak_flops()
    made = table(f"A splat training step: {rows['tiles']['splats']:,} splats at "
                 f"{rows['tiles']['size']}, {rows['tiles']['pairs']:,} pairs "
                 f"(median of {args.steps})",
                 ["CPU path", "step s", "draw s", "backward s", "pairs / s (step)",
                  "share of the roofline", "peak MB"],
                 [[NAMES[mode], round(r["step_s"], 3), round(r["draw_s"], 3),
                   round(r["backward_s"], 3), f"{r['pairs'] / r['step_s']:.3g}",
                   f"{100 * r['pairs'] * OPS_PER_PAIR / r['step_s'] / peak:.1f} %",
                   round(r["peak_mb"])] for mode, r in rows.items()])
    speed_up = rows["pairs"]["step_s"] / rows["tiles"]["step_s"]
    print(f"numba {speed_up:.1f} times as fast a step; machine peak {peak / 1e9:.1f} GFLOP/s "
          f"of scalar fused multiply-adds on {rows['tiles']['threads']} threads")
    write_result("rasteriser", "The CPU splat rasteriser: numba against PyTorch", [made],
                 {"modes": rows, "speed_up": speed_up, "peak_flops": peak,
                  "ops_per_pair": OPS_PER_PAIR})


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
