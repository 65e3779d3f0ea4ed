"""Structure from motion against Blender's own cameras: how many renders of a benchmark scene
register, how far the estimated poses lie from the true ones, and what training on them costs.

Renders the scene (``bench_scenes.render_scene``), copies all its views (train, val and test,
named ``SPLIT_FILE``) into one folder of photos and runs ``nerf-stage poses`` on it in a
fresh process, timed. The poses are scored against Blender's (``metrics.pose_errors``, after
the similarity that best maps the estimated camera centres onto the true ones; centre errors
in scene units and as a share of the cameras' mean distance from their centroid). Then the
same config trains twice, on Blender's poses and on the estimated ones (the same splits,
through nerfstudio's split lists; each decomposed from its own training images), and each
run is scored on its own held-out views: on the training path (``val``) and off it
(``test``), beside the scene's noise floor.

    python benchmarks/bench_poses.py [--out benchmarks/out/poses] [--scene garden]
        [--resolution 256] [--spp 16] [--camera-model SIMPLE_RADIAL] [--iters P F]

Needs Debian's ``blender`` (or PyPI's ``bpy``) and pycolmap (the ``poses`` extra).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_scenes import SPLITS, noise_floor, render_scene, rendered
from results import table, write_result

from nerf_stage.data.dataset import load_dataset
from nerf_stage.train.config import TrainConfig
from nerf_stage.train.loading import load_run
from nerf_stage.train.metrics import image_scores, pose_errors
from nerf_stage.train.trainer import train
from palette_core import decompose, read_stack


def photo_folder(scene: Path, data, out: Path) -> Path:
    """Every view of ``data`` copied into ``out`` as ``SPLIT_FILE`` (once)."""
    if not out.is_dir():
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix=f".{out.name}.", dir=out.parent) as staging:
            for name, split in zip(data.names, data.splits):
                shutil.copyfile(scene / name, Path(staging) / f"{split}_{Path(name).name}")
            os.rename(staging, out)  # the emptied temporary name is then gone
    return out


def estimated_dataset(capture: Path):
    """The capture with nerfstudio split lists from its photos' names, and its weights."""
    transforms = json.loads((capture / "transforms.json").read_text())
    names = [frame["file_path"] for frame in transforms["frames"]]
    for split in ("train", *SPLITS):
        transforms[f"{split}_filenames"] = [n for n in names
                                            if Path(n).name.startswith(f"{split}_")]
    (capture / "transforms.json").write_text(json.dumps(transforms, indent=1))
    if not (capture / "weights.npz").exists():
        decompose([capture / n for n in transforms["train_filenames"]], k=6).write(
            capture / "weights.npz")
    return load_dataset(capture), read_stack(capture / "weights.npz")


def error_figure(order: np.ndarray, rotation: np.ndarray, centre: np.ndarray, path: Path):
    """Rotation error (degrees) and centre error (share of the rig's size) per registered
    photo, in capture order (training views around the ring, then the held-out ones)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sort = np.argsort(order)
    figure, axes = plt.subplots(1, 2, figsize=(10, 3.2))
    for ax, values, label in ((axes[0], rotation, "rotation error (degrees)"),
                              (axes[1], 100 * centre, "centre error (% of the rig's size)")):
        ax.plot(values[sort], ".-")
        ax.set_xlabel("registered photo, in capture order")
        ax.set_ylabel(label)
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def trained_scores(label: str, config: TrainConfig, data, stack, out: Path) -> dict:
    run_dir = out / label
    if not (run_dir / "checkpoint.pt").exists():
        train(config, data, stack, run_dir, force=True)
    run = load_run(run_dir)
    scores = {split: image_scores(rendered(run, data, data.indices(split)),
                                  data.images[data.indices(split)])
              for split in SPLITS if len(data.indices(split))}  # views that registered
    scores["seconds"] = run.record.log[-1]["seconds"]
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/poses"))
    parser.add_argument("--scene", default="garden")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--camera-model", default="SIMPLE_RADIAL")
    parser.add_argument("--iters", type=int, nargs=2, default=None, metavar=("P", "F"))
    args = parser.parse_args()
    scene = render_scene(args.scene, args.out, args.resolution, args.spp)
    truth = load_dataset(scene)
    photos = photo_folder(scene, truth, args.out / f"{scene.name}-photos")
    capture = args.out / f"{scene.name}-capture-{args.camera_model}"
    if not (capture / "transforms.json").exists():
        start = time.perf_counter()
        subprocess.run(["nerf-stage", "poses", str(photos), "-o", str(capture),
                        "--camera-model", args.camera_model], check=True)
        print(f"nerf-stage poses: {time.perf_counter() - start:.1f} s wall, in a fresh "
              "process", flush=True)
    data, stack = estimated_dataset(capture)
    by_name = {f"{split}_{Path(name).name}": i
               for i, (name, split) in enumerate(zip(truth.names, truth.splits))}
    matched = [by_name[Path(name).name] for name in data.names]
    rotation, centre = pose_errors(data.poses, truth.poses[matched])
    centres = truth.poses[matched, :3, 3]
    spread = np.linalg.norm(centres - centres.mean(0), axis=1).mean()
    missing = sorted(set(by_name) - {Path(name).name for name in data.names})
    results = {"registered": len(data.names), "photos": len(truth.names), "missing": missing,
               "rotation_degrees": [float(np.median(rotation)), float(rotation.max())],
               "centre_error": [float(np.median(centre)), float(centre.max())],
               "centre_error_share": [float(np.median(centre) / spread),
                                      float(centre.max() / spread)]}
    print(f"registered {len(data.names)} of {len(truth.names)}; rotation error median "
          f"{np.median(rotation):.3f} deg, worst {rotation.max():.3f} deg; centre error median "
          f"{np.median(centre):.4f}, worst {centre.max():.4f} scene units "
          f"({100 * np.median(centre) / spread:.2f} % and {100 * centre.max() / spread:.2f} % "
          "of the cameras' mean distance from their centroid)"
          + (f"; not registered: {', '.join(missing)}" if missing else ""), flush=True)
    error_figure(np.asarray(matched), rotation, centre / spread,  # Blender's frame order
                 args.out / f"{scene.name}-pose-errors.png")
    floor = {split: noise_floor(truth, split) for split in SPLITS}
    results["floor"] = floor
    print("noise floor (Blender's views under another sampler seed): "
          + ", ".join(f"{s} {floor[s]['psnr']:.2f} dB" for s in SPLITS), flush=True)
    config = TrainConfig(**dict(zip(("pretrain_iters", "finetune_iters"), args.iters or ())))
    truth_stack = read_stack(scene / "weights.npz")
    for label, dataset, weights in (("blender-poses", truth, truth_stack),
                                    (f"estimated-poses-{args.camera_model}", data, stack)):
        scores = trained_scores(f"{scene.name}-{label}", config, dataset, weights, args.out)
        results[label] = scores
        print(f"{label}: " + ", ".join(f"{s} {scores[s]['psnr']:.2f} dB / SSIM "
                                       f"{scores[s]['ssim']:.3f}" if s in scores else
                                       f"{s}: no view registered" for s in SPLITS)
              + f", trained in {scores['seconds']:.0f} s", flush=True)
    poses = table(f"{scene.name}: poses against Blender's ({args.camera_model})",
                  ["registered", "rotation median (deg)", "rotation worst (deg)",
                   "centre median (share)", "centre worst (share)"],
                  [[f"{results['registered']} of {results['photos']}",
                    *results["rotation_degrees"], *results["centre_error_share"]]])
    trained = table(f"{scene.name}: trained on each set of poses (PSNR dB / SSIM)",
                    ["poses", *SPLITS, "noise floor", "training s"],
                    [[label, *(f"{scores[s]['psnr']:.2f} / {scores[s]['ssim']:.3f}"
                               if s in scores else "none registered" for s in SPLITS),
                      ", ".join(f"{s} {floor[s]['psnr']:.2f}" for s in SPLITS),
                      round(scores["seconds"])]
                     for label, scores in results.items() if label.endswith("poses")
                     or label.startswith("estimated-poses")])
    write_result(f"poses-{scene.name}", "Structure from motion against Blender's cameras",
                 [poses, trained], results)


if __name__ == "__main__":
    sys.exit(main())
