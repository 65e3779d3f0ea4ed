"""Real photo captures: held-out PSNR and SSIM of our palette NeRF (two-stage), our RGB
NeRF (``--strategy rgb``, the paper's Table 3 baseline) and nerfstudio's nerfacto, each
trained for the same wall-clock budget on the same photos, poses and held-out views, with
the peak memory of our training and a picture per capture and method.

The captures are folders in ROOT, one per name, that you fill once with the search tool's
``fetch`` (no program of ours downloads anything; none of them is committed):

- ``fox``: NVlabs/instant-ngp ``data/nerf/fox`` (phone photos of a fox figure, with
  ``transforms.json``: poses and ``k1 k2 p1 p2``; it names 67 frames, of which the
  repository holds 50 photos: keep the frames whose photo it holds), its points
  triangulated by ``nerf-stage poses ROOT/fox -o ROOT2/fox`` for the splats;
- ``lund``: mapillary/OpenSfM ``data/lund/images`` (29 photos walking down a street);
- ``sceaux``: openMVG/ImageDataset_SceauxCastle ``images`` (11 photos of a castle front);
- ``monstree``: alicevision/dataset_monstree ``full`` (photos around a tree; the mirror
  holds 23 of its 41).

A folder with a ``transforms.json`` is posed; a folder of photos gets its poses from
``nerf-stage poses``. Each capture is then written again at 1/``--downscale`` of its size,
undistorted, as PNGs in nerfstudio's layout with every eighth photo held out in its
``test_filenames`` (``OUT/NAME/data``): both NeRF codes read those same pixels, poses and
splits. ``palette-decompose -k 6`` makes the weight stack of its photos.

Budget: each method trains for ``--minutes``. Ours: a short probe run measures the
seconds an iteration takes, the pretrain and fine-tune iterations are set to fill the
budget, and ``--minutes`` with ``--pretrain-minutes`` ends each stage at its share, in
the defaults' ratio (``ours``).
nerfacto (PyTorch implementation, ``--machine.device-type cpu`` without CUDA) runs in its
own virtual environment, ``--nerfacto-venv``, which this script creates when missing
(PyPI's ``nerfstudio``; never a dependency of ours), and is stopped by the clock: its
learning-rate schedules do not depend on its ``--max-num-iterations`` (they run over
200,000 steps), so that its run ends, its checkpoint saved, at the first iteration after
the budget. Its held-out views are rendered by ``ns-eval`` into PNGs and scored here, by
the same ``image_scores`` as ours.

    python benchmarks/bench_captures.py ROOT [--out benchmarks/out/captures]
        [--captures fox lund sceaux monstree] [--minutes 20] [--downscale 4]
        [--methods palette rgb nerfacto] [--backbone grid|hash|splats]
        [--curve-points 10] [--train-options '--batch-rays 16384']
        [--nerfacto-venv benchmarks/out/nerfacto-venv]

Scores: PSNR and SSIM, and PSNR after each render's affine colour fit to its photo
(``psnr_cc``, ``metrics.colour_corrected``): the training photos' exposures are learned,
a held-out photo's are not, and cameras set them photo by photo.

Writes ``benchmarks/results/captures.json`` (every capture and method in OUT so far),
``OUT/results.json`` (the same, kept between calls), ``OUT/NAME-METHOD.png`` (held-out
views: truth | render | absolute error x4 | for ours, how many training views see each
pixel's surface, black for none, white for four or more: ``views_seeing``, whose PSNR by
count the results hold as ``by_views_seeing``) and ``OUT/NAME-curve.png`` (held-out PSNR
against training time: our runs' checkpoints, nerfacto's end). Runs are cached in OUT by
capture and method.
"""

from __future__ import annotations

import argparse
import json
import re
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_scenes import Snapshots, checkpoint_curve, curve_picture, error_map, rendered
from nerfacto import nerfacto, run_command
from PIL import Image
from results import table, write_result

from nerf_stage.backbones import BACKBONES
from nerf_stage.data.cameras import project
from nerf_stage.data.dataset import load_dataset
from nerf_stage.data.points import POINTS_FILE, write_points
from nerf_stage.train.config import TrainConfig
from nerf_stage.train.loading import load_run
from nerf_stage.train.metrics import image_scores, psnr_from_mse

CAPTURES = ("fox", "lund", "sceaux", "monstree")
METHODS = ("palette", "rgb", "nerfacto")
PROBE_ITERS = 40  # iterations of the probe that times our NeRF
SPEED_UP = 2.0  # how much faster iterations run than the probe's (the occupancy grid prunes)
#: Iterations planned beyond the expected ones: every stage ends by the clock, its learning
#: rates decayed by it and a splat run's densification stopped at its share of the stage's
#: time (``trainer.stage_progress``), so a plan far longer than the budget costs nothing and
#: leaves the clock to end the stage (a field's iterations speed up from capture to capture
#: by up to ten times once space is pruned).
HEADROOM = 10.0
#: A held-out pixel's surface is seen by a training view that has it in its frame and at
#: most this many times as far as the surface it shows at that pixel (``views_seeing``).
SEEN_DEPTH = 1.05
PRETRAIN_SHARE = TrainConfig().pretrain_iters / TrainConfig().total_iters
BIN = Path(sys.executable).parent


def posed(source: Path, out: Path) -> Path:
    """``source`` if it holds a ``transforms.json``, else its photos posed into ``out``."""
    if (source / "transforms.json").is_file():
        return source
    if not (out / "transforms.json").is_file():
        run_command([BIN / "nerf-stage", "poses", source, "-o", out, "--force"], "poses")
    return out


def undistorted_beforehand(capture: Path, out: Path) -> Path:
    """``capture`` (nerfstudio layout, one OpenCV lens) undistorted by COLMAP's own
    undistorter into the COLMAP project ``out`` (``images/``, ``sparse/``): the reference
    that our undistortion on reading is measured against."""
    from scipy.spatial.transform import Rotation

    from nerf_stage.data.colmap import import_pycolmap

    if not (out / "sparse").is_dir():
        meta = json.loads((capture / "transforms.json").read_text())
        model = out.with_name(out.name + "-distorted")
        model.mkdir(parents=True, exist_ok=True)
        lens = " ".join(str(meta.get(key, 0.0)) for key in ("k1", "k2", "p1", "p2"))
        (model / "cameras.txt").write_text(
            f"1 OPENCV {meta['w']:.0f} {meta['h']:.0f} {meta['fl_x']} {meta['fl_y']} "
            f"{meta['cx']} {meta['cy']} {lens}\n")
        lines = []
        for i, frame in enumerate(meta["frames"]):
            to_world = np.array(frame["transform_matrix"], float)
            to_world[:3, 1:3] *= -1  # OpenGL camera axes to OpenCV's
            to_camera = np.linalg.inv(to_world)
            x, y, z, w = Rotation.from_matrix(to_camera[:3, :3]).as_quat()
            name = Path(frame["file_path"]).name
            lines.append(f"{i + 1} {w} {x} {y} {z} {' '.join(map(str, to_camera[:3, 3]))} "
                         f"1 {name}\n\n")
        (model / "images.txt").write_text("".join(lines))
        (model / "points3D.txt").write_text("")
        import_pycolmap().undistort_images(out, model, capture / "images")
    return out


def small_capture(capture: Path, out: Path, downscale: int) -> Path:
    """``capture`` at 1/``downscale`` of its size, undistorted, in PNGs with its splits
    named in ``transforms.json`` (written once), its sparse points where it has them, and
    its weight stack."""
    if not (out / "weights.npz").is_file():
        data = load_dataset(capture, downscale=downscale)
        (out / "images").mkdir(parents=True, exist_ok=True)
        frames, splits = [], {"train": [], "test": []}
        for i in range(len(data.names)):
            path = f"images/{i:04d}.png"
            Image.fromarray((data.images[i] * 255).round().astype(np.uint8)).save(out / path)
            camera = data.camera(i)
            frames.append({"file_path": path, "transform_matrix": data.poses[i].tolist(),
                           "fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx,
                           "cy": camera.cy})
            splits["test" if data.splits[i] == "test" else "train"].append(path)
        points = {}
        if data.points is not None:  # the start of splat runs (nerfstudio's sparse_pc.ply)
            write_points(data.points, out / POINTS_FILE)
            points = {"ply_file_path": POINTS_FILE}
        (out / "transforms.json").write_text(json.dumps({
            "camera_model": "PINHOLE", "w": data.intrinsics.width, "h": data.intrinsics.height,
            "frames": frames, "train_filenames": splits["train"],
            "val_filenames": splits["test"], "test_filenames": splits["test"], **points},
            indent=1))
        run_command([BIN / "palette-decompose", out / "images", "-k", "6", "-o",
                     out / "weights.npz", "--force"], "decompose")
    return out


def ours(data_dir: Path, run_dir: Path, strategy: str, backbone: str, seconds: float,
         curve_points: int = 10, options: tuple[str, ...] = (),
         share: float = PRETRAIN_SHARE) -> dict:
    """Train our NeRF (``backbone``) on ``data_dir`` within ``seconds``; its renders of the
    held-out views, iterations, training seconds, peak memory and held-out PSNR against
    training time (``curve``: seconds and dB of about ``curve_points`` checkpoints; 0: the
    end alone); ``options``: more of ``nerf-stage train``'s, for the probe and the run;
    ``share``: the first stage's share of the iterations and of ``seconds``.

    ``nerf-stage train --minutes`` ends each stage at its share of the budget, its learning
    rates then decayed as at the stage's last iteration. The iterations come from the rate
    of the second half of a probe run's first stage (past the first iterations' warm-up,
    before a splat run's palette stage draws its footprints), times ``SPEED_UP``
    (iterations speed up as the occupancy grid prunes empty space) and ``HEADROOM``. A run
    whose iterations end first reports the time it took."""
    snapshots = run_dir.with_name(run_dir.name + "-snapshots")
    log = run_dir.with_name(run_dir.name + ".log")  # nerf-stage train's output
    data = load_dataset(data_dir)
    test = data.indices("test")
    if not (run_dir / "checkpoint.pt").is_file():
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=".probe-", dir=run_dir.parent) as probe:
            _train(data_dir, Path(probe) / "run", strategy, backbone,
                   PROBE_ITERS * PRETRAIN_SHARE, PROBE_ITERS * (1 - PRETRAIN_SHARE), 0.0,
                   PRETRAIN_SHARE, options=options)
            probed = load_run(Path(probe) / "run").record.log
        # the first stage's second half: past the warm-up, and before the palette stage's
        # start (a splat run's footprints of every view) that the rate would count
        probed = [entry for entry in probed if entry["stage"] == probed[0]["stage"]]
        probed = probed[len(probed) // 2:]
        rate = (len(probed) - 1) / (probed[-1]["seconds"] - probed[0]["seconds"])
        expected = SPEED_UP * seconds * rate
        # a splat run's rgb strategy trains its first stage alone
        first = HEADROOM * (1 if strategy == "rgb" else share)
        with Snapshots(run_dir / "checkpoint.pt", snapshots):
            _train(data_dir, run_dir, strategy, backbone, expected * first,
                   expected * HEADROOM * (1 - share), seconds / 60, share,
                   every=max(1, round(expected / max(1, curve_points))), log=log,
                   options=options)
    curve = checkpoint_curve(snapshots, data, test) if curve_points else []
    run = load_run(run_dir)
    memory = re.search(r"peak memory ([\d.]+) GB", log.read_text() if log.is_file() else "")
    rendered(run, data, test[:1])  # warm-up, so that the rate below is of renders alone
    start = time.perf_counter()
    render = rendered(run, data, test)
    fps = len(test) / (time.perf_counter() - start)
    return {"render": render, "curve": curve, "render_fps": fps,
            "seen": views_seeing(run, data, test),
            "iterations": len(run.record.log), "seconds": run.record.log[-1]["seconds"],
            "peak_gb": float(memory.group(1)) if memory else None}


def views_seeing(run, data, ids) -> np.ndarray:
    """(N, H, W) how many training views of ``data`` see the surface that each pixel of its
    views ``ids`` shows in ``run`` (``PixelSamples.median_points``): with it in their frame,
    not behind the surface they show there (``SEEN_DEPTH``). Where none or one does, the
    photos do not place what the pixel shows."""
    def surfaces(views):  # each view's camera and (H, W, 3) surface points
        for view in views:
            camera = data.camera(view)
            _, opacity, samples = run.render(data.poses[[view]], intrinsics=camera,
                                             samples=True)
            yield view, camera, samples.median_points(opacity.size).reshape(
                camera.height, camera.width, 3)

    depths = [(view, camera, project(points.reshape(-1, 3), data.poses[view], camera)[2]
               .reshape(points.shape[:2]))
              for view, camera, points in surfaces(data.indices("train"))]
    counts = []
    for _, _, points in surfaces(ids):
        flat, count = points.reshape(-1, 3), 0
        for view, camera, depth in depths:
            x, y, z = project(flat, data.poses[view], camera)
            inside = (z > 0) & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
            there = depth[np.where(inside, y, 0).astype(int), np.where(inside, x, 0).astype(int)]
            count = count + (inside & ~(z > SEEN_DEPTH * there))  # NaN: nothing drawn there
        counts.append(np.reshape(count, points.shape[:2]))
    return np.stack(counts)


def scores_by_views_seeing(truth: np.ndarray, render: np.ndarray, seen: np.ndarray) -> dict:
    """Share of the held-out pixels and their PSNR where ``seen`` (``views_seeing``) is 0,
    1 and 2 or more."""
    error = np.mean((render - truth) ** 2, axis=-1)
    scores = {}
    for name, mask in (("0", seen == 0), ("1", seen == 1), ("2+", seen >= 2)):
        mse = float(error[mask].mean()) if mask.any() else None
        scores[name] = {"share": float(mask.mean()),
                        "psnr": psnr_from_mse(max(mse, 1e-10)) if mse is not None else None}
    return scores


def _train(data_dir: Path, run_dir: Path, strategy: str, backbone: str, pretrain: float,
           finetune: float, minutes: float, share: float, every: int = 500,
           log: Path | None = None, options: tuple[str, ...] = ()) -> str:
    """``nerf-stage train`` for ``pretrain`` and ``finetune`` iterations within ``minutes``
    (0: no limit), pretraining within ``share`` of them, with a checkpoint ``every`` so many
    iterations and more ``options``; its output (``_run``)."""
    return run_command([BIN / "nerf-stage", "train", data_dir, "-o", run_dir, "--force",
                 "--strategy", strategy, "--backbone", backbone,
                 "--pretrain-iters", str(max(1, round(pretrain))),
                 "--finetune-iters", str(max(1, round(finetune))),
                 "--minutes", str(minutes), "--pretrain-minutes", str(minutes * share),
                 "--checkpoint-every", str(every), *options],
                f"train {strategy}", log)


def trained(method: str, data_dir: Path, run_dir: Path, args) -> dict:
    """``method`` trained on ``data_dir`` for the budget of ``args`` (or its cached run in
    ``run_dir``): its held-out renders and what ``ours`` or ``nerfacto`` report."""
    seconds = 60 * args.minutes
    if method == "nerfacto":
        return nerfacto(data_dir, run_dir, seconds, args.nerfacto_venv.resolve())
    strategy = "two-stage" if method.startswith("palette") else "rgb"
    return ours(data_dir, run_dir, strategy, args.backbone, seconds, args.curve_points,
                tuple(args.train_options), args.pretrain_share)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("root", type=Path, help="folder of captures, one folder per name")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/captures"))
    parser.add_argument("--captures", nargs="+", default=list(CAPTURES))
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--minutes", type=float, default=20.0)
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--backbone", default="grid", choices=list(BACKBONES),
                        help="our NeRFs' backbone (methods palette and rgb; results under "
                             "palette-BACKBONE and rgb-BACKBONE unless grid)")
    parser.add_argument("--curve-points", type=int, default=10,
                        help="checkpoints of each of our runs scored on the held-out views for "
                             "the PSNR-against-time curve (0: the end alone)")
    parser.add_argument("--undistorted-beforehand", action="store_true",
                        help="benchmark NAME-undistorted beside each posed capture with a "
                             "lens: its photos undistorted by COLMAP, not by us")
    parser.add_argument("--train-options", type=shlex.split, default=(),
                        help="more options of nerf-stage train for our runs, in one string "
                             "(e.g. '--batch-rays 16384'; runs are cached by method: give "
                             "such runs their own --out)")
    parser.add_argument("--pretrain-share", type=float, default=PRETRAIN_SHARE,
                        help="our two-stage runs' share of the budget for their first stage "
                             "(default: the defaults' iterations' share, P / (P + F))")
    parser.add_argument("--nerfacto-venv", type=Path,
                        default=Path("benchmarks/out/nerfacto-venv"))
    args = parser.parse_args()
    if not 0 < args.pretrain_share < 1:
        parser.error(f"--pretrain-share must be in (0, 1), got {args.pretrain_share}")
    results_path = args.out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    captures = []
    for name in args.captures:
        capture = posed(args.root / name, args.out / name / "posed")
        captures.append((name, capture))
        lens = "k1" in json.loads((capture / "transforms.json").read_text())
        if args.undistorted_beforehand and lens:
            folder = args.out / f"{name}-undistorted"
            project = undistorted_beforehand(capture, folder / "colmap")
            captures.append((folder.name, posed(project, folder / "posed")))
    for name, capture in captures:
        folder = args.out / name
        data_dir = small_capture(capture, folder / "data", args.downscale)
        data = load_dataset(data_dir)
        truth = data.images[data.indices("test")]
        for method in args.methods:
            if method != "nerfacto" and args.backbone != "grid":  # runs named by backbone too
                method = f"{method}-{args.backbone}"
            result = trained(method, data_dir, folder / method, args)
            render, seen = result.pop("render"), result.pop("seen", None)
            result.update(image_scores(render, truth, corrected=True), views=len(truth),
                          size=f"{data.intrinsics.width}x{data.intrinsics.height}",
                          train_views=len(data.indices("train")))
            if seen is not None:
                result["by_views_seeing"] = scores_by_views_seeing(truth, render, seen)
            error_map(truth, render, args.out / f"{name}-{method}.png", seen=seen)
            results.setdefault(name, {})[method] = result
            print(f"{name} {method}: PSNR {result['psnr']:.2f} dB ({result['psnr_cc']:.2f} "
                  f"colour-corrected), SSIM {result['ssim']:.4f} "
                  f"on {len(truth)} held-out views at {result['size']}; "
                  f"{result['iterations']} iterations in {result['seconds']:.0f} s"
                  + (f", peak {result['peak_gb']:.2f} GB" if result.get("peak_gb") else "")
                  + (f", renders {result['render_fps']:.1f} views/s"
                     if result.get("render_fps") else ""),
                  flush=True)
            args.out.mkdir(parents=True, exist_ok=True)
            results_path.write_text(json.dumps(results, indent=1))
        curve_picture(results[name], f"{name}, {results[name][method]['size']}, "
                      f"{len(truth)} held-out views", args.out / f"{name}-curve.png")
    made = table(f"Held-out views at 1/{args.downscale} size, {args.minutes:g} minutes a method",
                 ["capture", "method", "size", "iterations", "training s", "PSNR",
                  "PSNR colour-corrected", "SSIM", "peak GB"],
                 [[name, method, r["size"], r["iterations"], round(r["seconds"]),
                   round(r["psnr"], 2), round(r["psnr_cc"], 2), round(r["ssim"], 3),
                   r.get("peak_gb") and round(r["peak_gb"], 2)]
                  for name, methods in results.items() for method, r in methods.items()])
    write_result("captures", "Real photo captures against nerfacto", [made], results)


if __name__ == "__main__":
    main()
