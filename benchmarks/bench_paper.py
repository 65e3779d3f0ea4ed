"""The paper's Table 3 on its own public scenes: held-out PSNR and SSIM of our palette NeRF
(``two-stage``) with each backbone, and of an RGB NeRF of ours (``--strategy rgb``, the
paper's NeRF column), each trained for ``--minutes``, beside the paper's numbers.

The scenes are folders in ROOT that you fill once with the search tool's ``fetch`` (none is
committed; no program of ours downloads anything):

- ``lego``: NeRF-synthetic ``lego`` (``data/nerf_synthetic/lego`` of
  ``luo-ziyuan/CopyRNeRF-code`` or ``Zephyrmcb/NeRF-Pytorch``: ``transforms_*.json``,
  ``train/``, ``test/``), read at 1 / ``--lego-downscale`` of its 800 x 800 (4: 200 x 200)
  and scored on every ``--lego-every`` th of its 200 test views (8 on a CPU; 1: all);
- ``flower`` (``data/flower`` of ``zhelianl-zl/deeplearning_Nerf``) and ``orchids``
  (``data/nerf_llff_data/orchids`` of ``Zephyrmcb/NeRF-Pytorch``): LLFF captures,
  ``poses_bounds.npy`` with the full photos in ``images/`` (and, for the flower, LLFF's own
  ``images_8/``), read at 1 / ``--llff-downscale`` (8: 504 x 378), every eighth photo held
  out (LLFF's split). A scene's ``images_N`` of LLFF is used when it is there; otherwise
  the full photos are resized (Lanczos, as LLFF's ``mogrify`` makes them).

Each scene is written again into OUT (the images at their size, the split) and decomposed
(``palette-decompose -k 6``); each run is ``nerf-stage train --minutes M`` (its iterations
planned for the budget), its held-out views rendered and scored (``metrics.image_scores``),
a picture a run (``OUT/SCENE-RUN.png``: truth | render | error x 4) and, with
``--curve-every``, the held-out PSNR at its checkpoints against training time
(``OUT/SCENE-curve.png``).

    python benchmarks/bench_paper.py ROOT [--scenes lego flower orchids]
        [--backbones grid splats] [--rgb-backbone splats] [--runs SCENE:RUN ...]
        [--minutes 20] [--curve-every 2000]

A run named ``grid@ndc`` trains the grid in NDC space (``--space ndc``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np
from bench_scenes import Snapshots, checkpoint_curve, curve_picture, error_map, rendered
from PIL import Image
from results import RESULTS, commit, table, write_result

from nerf_stage.data.dataset import load_dataset
from nerf_stage.train.config import TrainConfig
from nerf_stage.train.loading import load_run
from nerf_stage.train.metrics import image_scores
from nerf_stage.train.trainer import train
from palette_core.cli.decompose import main as decompose
from palette_core.folders import files_in
from palette_core.outputs import publish_folder
from palette_core.stack import read_stack

SCENES = ("lego", "flower", "orchids")
#: The paper's Table 3: (PSNR, SSIM) of NeRF and of PaletteNeRF.
PAPER = {"lego": ((31.153, 0.952), (30.135, 0.941)),
         "flower": ((28.147, 0.887), (28.172, 0.881)),
         "orchids": ((21.325, 0.750), (21.515, 0.759))}


def prepared(root: Path, scene: str, out: Path, args) -> Path:
    """``scene`` of ``root`` written into ``out`` at the benchmark's size, with its stack."""
    if (out / "weights.npz").is_file():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with publish_folder(out) as staging:
        photos = (_nerf_synthetic(root / scene, staging, args.lego_downscale, args.lego_every)
                  if scene == "lego" else _llff(root / scene, staging, args.llff_downscale))
        if decompose([str(photos), "-k", "6", "-o", str(staging / "weights.npz")]) != 0:
            sys.exit(f"palette-decompose failed on {photos}")
    return out


def _nerf_synthetic(source: Path, out: Path, factor: int, every: int) -> Path:
    """The train split and every ``every`` th test view, at 1 / ``factor`` (block means of
    the RGBA, as ``cv2.INTER_AREA``), in ``out / "images"``, which is returned."""
    (out / "images").mkdir()
    for split, keep in (("train", 1), ("test", every)):
        meta = json.loads((source / f"transforms_{split}.json").read_text())
        frames = meta["frames"][::keep]
        for frame in frames:
            name = Path(frame["file_path"]).name + ".png"
            image = np.asarray(Image.open(source / split / name).convert("RGBA"), np.float32)
            h, w = image.shape[0] // factor, image.shape[1] // factor
            small = image[:h * factor, :w * factor].reshape(h, factor, w, factor, 4).mean((1, 3))
            Image.fromarray(small.round().astype(np.uint8)).save(out / "images" / f"{split}_{name}")
            frame["file_path"] = f"images/{split}_{Path(name).stem}"
        (out / f"transforms_{split}.json").write_text(json.dumps(
            {"camera_angle_x": meta["camera_angle_x"], "frames": frames}, indent=1))
    return out / "images"


def _llff(source: Path, out: Path, factor: int) -> Path:
    """``poses_bounds.npy`` and the photos at 1 / ``factor`` in ``out / "images_N"``, which
    is returned: LLFF's ``images_N`` when the capture has it, else the full photos resized
    (Lanczos)."""
    shutil.copy(source / "poses_bounds.npy", out / "poses_bounds.npy")
    target = out / f"images_{factor}"
    target.mkdir()
    if (source / f"images_{factor}").is_dir():  # its files only: a link out is refused
        for path in files_in(source / f"images_{factor}", recursive=False):
            shutil.copyfile(path, target / path.name)
        return target
    for i, path in enumerate(files_in(source / "images", recursive=False)):
        image = Image.open(path).convert("RGB")
        image.resize((image.width // factor, image.height // factor), Image.LANCZOS).save(
            target / f"image{i:03d}.png")
    return target


def scored(data_dir: Path, run_dir: Path, config: TrainConfig, curve: bool) -> dict:
    """``config`` trained on ``data_dir`` into ``run_dir`` (reused when it is there) and
    scored on the held-out views; with ``curve``, the held-out PSNR at each checkpoint."""
    data = load_dataset(data_dir, config.background)
    test = data.indices("test")
    snapshots = run_dir.with_name(run_dir.name + "-snapshots")
    if not (run_dir / "checkpoint.pt").is_file():
        with (Snapshots(run_dir / "checkpoint.pt", snapshots) if curve
              else contextlib.nullcontext()):
            train(config, data, read_stack(data_dir / "weights.npz"), run_dir, force=True)
    run = load_run(run_dir)
    render = rendered(run, data, test)
    scores = image_scores(render, data.images[test])
    error_map(data.images[test], render, run_dir.with_suffix(".png"))
    return {**scores, "iterations": len(run.record.log),
            "rgb_iterations": sum(entry.get("stage") == "rgb" for entry in run.record.log),
            "planned": run.config.total_iters,
            "seconds": run.record.log[-1]["seconds"], "views": len(test),
            "size": f"{data.intrinsics.width}x{data.intrinsics.height}",
            "curve": checkpoint_curve(snapshots, data, test) if curve else []}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("root", type=Path, help="folder of the scenes, one folder a name")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/paper"))
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    parser.add_argument("--backbones", nargs="+", default=["grid", "splats"])
    parser.add_argument("--rgb-backbone", default="splats",
                        help="the backbone of the RGB NeRF column (none: no such run)")
    parser.add_argument("--minutes", type=float, default=20.0)
    parser.add_argument("--lego-downscale", type=int, default=4)
    parser.add_argument("--lego-every", type=int, default=8)
    parser.add_argument("--llff-downscale", type=int, default=8)
    parser.add_argument("--runs", nargs="+", metavar="SCENE:RUN",
                        help="these runs only (RUN: a backbone, or BACKBONE-rgb, either "
                             "with @SPACE for a --space other than auto), instead of every "
                             "scene with every backbone")
    parser.add_argument("--curve-every", type=int, default=2000,
                        help="iterations between the checkpoints scored for the curves (0: "
                             "none)")
    args = parser.parse_args()
    names = [*args.backbones, *([f"{args.rgb_backbone}-rgb"] if args.rgb_backbone != "none"
                                else [])]
    runs = ([tuple(run.split(":")) for run in args.runs] if args.runs else
            [(scene, name) for scene in args.scenes for name in names])
    if any(len(run) != 2 or run[0] not in SCENES for run in runs):
        parser.error(f"--runs are SCENE:RUN with a scene of {', '.join(SCENES)}")
    results = earlier_results()
    for scene in dict.fromkeys(scene for scene, _ in runs):
        data_dir = prepared(args.root, scene, args.out / scene, args)
        results.setdefault(scene, {})
        for name in [name for other, name in runs if other == scene]:
            kind, _, space = name.partition("@")
            backbone, _, rgb = kind.partition("-")
            config = TrainConfig(backbone=backbone, strategy="rgb" if rgb else "two-stage",
                                 space=space or "auto", minutes=args.minutes,
                                 checkpoint_every=args.curve_every or 10**6)
            result = scored(data_dir, args.out / f"{scene}-{name}", config,
                            bool(args.curve_every))
            results[scene][name] = {**result, "minutes": args.minutes, "commit": commit()}
            print(f"{scene} {name}: PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.3f} on "
                  f"{result['views']} views at {result['size']}; {result['iterations']} "
                  f"iterations in {result['seconds']:.0f} s", flush=True)
        if args.curve_every:
            curve_picture(results[scene], f"{scene}, held-out views",
                          args.out / f"{scene}-curve.png")
    rows = [[scene, run["size"], name, round(run["psnr"], 2), round(run["ssim"], 3),
             run["iterations"], run.get("rgb_iterations", ""), round(run["seconds"] / 60, 1),
             *PAPER[scene][1], *PAPER[scene][0]]
            for scene in SCENES for name, run in results.get(scene, {}).items()]
    made = table("Held-out views, a run trained for its minutes on the machine below",
                 ["scene", "size", "ours", "PSNR", "SSIM", "iterations", "of them RGB", "minutes",
                  "PaletteNeRF PSNR", "SSIM", "NeRF PSNR", "SSIM"], rows)
    write_result("paper", "The paper's Table 3 on its own scenes", [made], results)


def earlier_results() -> dict:
    """The runs of ``results/paper.json`` (a run scored again replaces its own), so that the
    table grows one run at a time."""
    path = RESULTS / "paper.json"
    return json.loads(path.read_text())["results"] if path.is_file() else {}


if __name__ == "__main__":
    main()
