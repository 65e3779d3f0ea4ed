"""Weight NeRFs on scenes rendered by Blender's Cycles (``benchmarks/scenes/``), not by our
path tracer: test PSNR and SSIM against each scene's noise floor, per scene space.

For each scene: render it (once; ``blender -b --factory-startup -P SCRIPT -- DIR``), measure
the noise floor (its test views against the same views rendered under another sampler
seed, ``test_seed2/``), decompose its training views (``palette-decompose -k 6``), then
train a weight NeRF per ``--space`` and score it on the test views (off the training path),
saving an error map of each run's first test views (``OUT/SCENE-SPACE-errors.png``: truth,
render, absolute error x4).

    python benchmarks/bench_scenes.py [--out benchmarks/out/scenes] [--scenes garden]
        [--spaces box unbounded] [--iters P F]

Needs Debian's ``blender`` (or PyPI's ``bpy``); runs are cached in OUT by scene and space.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

from nerf_stage.config import TrainConfig
from nerf_stage.data import load_dataset
from nerf_stage.editing import WeightRender
from nerf_stage.evaluation import evaluate
from nerf_stage.metrics import image_scores
from nerf_stage.run import load_run
from nerf_stage.trainer import train
from palette_core import decompose, read_stack

SCENES = Path(__file__).parent / "scenes"


def noise_floor(scene: Path) -> dict:
    """Scores of the test views against their renders under another sampler seed."""
    data = load_dataset(scene)
    names = [data.names[i] for i in data.indices("test")]
    again = np.stack([np.asarray(Image.open(scene / "test_seed2" / Path(n).name).convert("RGB"),
                                 np.float32) / 255 for n in names])
    return image_scores(again, data.images[data.indices("test")])


def render_scene(name: str, out: Path) -> Path:
    scene = out / name
    if not (scene / "transforms_test.json").exists():
        start = time.perf_counter()
        subprocess.run(["blender", "-b", "--factory-startup", "-P", str(SCENES / f"{name}.py"),
                        "--", str(scene)], check=True, stdout=subprocess.DEVNULL)
        print(f"{name}: rendered in {time.perf_counter() - start:.0f} s", flush=True)
    if not (scene / "weights.npz").exists():
        decompose([scene / "train"], k=6).write(scene / "weights.npz")
    return scene


def error_map(run_dir: Path, scene: Path, path: Path, views: int = 3) -> None:
    run, data = load_run(run_dir), load_dataset(scene)
    test = data.indices("test")[:views]
    values, opacity = run.render(data.poses[test], progress=False)
    render = WeightRender(values, opacity, [data.names[i] for i in test], run.palette,
                          run.basis, run.order, np.asarray(run.config.background), {}).recolor()
    truth = data.images[test]
    rows = [np.concatenate([t, r, np.clip(4 * np.abs(r - t), 0, 1)], 1)
            for t, r in zip(truth, render)]
    picture = (np.concatenate(rows, 0) * 255).round().astype(np.uint8)
    Image.fromarray(picture).resize((picture.shape[1] * 2, picture.shape[0] * 2),
                                    Image.NEAREST).save(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/scenes"))
    parser.add_argument("--scenes", nargs="+", default=sorted(p.stem for p in SCENES.glob("*.py")))
    parser.add_argument("--spaces", nargs="+", default=["box", "unbounded"])
    parser.add_argument("--iters", type=int, nargs=2, default=None, metavar=("P", "F"))
    args = parser.parse_args()
    results = {}
    for name in args.scenes:
        scene = render_scene(name, args.out)
        floor = noise_floor(scene)
        print(f"{name}: noise floor {floor['psnr']:.2f} dB, SSIM {floor['ssim']:.3f}", flush=True)
        data, stack = load_dataset(scene), read_stack(scene / "weights.npz")
        for space in args.spaces:
            config = TrainConfig(space=space)
            if args.iters:
                config.pretrain_iters, config.finetune_iters = args.iters
            run_dir = args.out / f"{name}-{space}"
            if not (run_dir / "checkpoint.pt").exists():
                train(config, data, stack, run_dir, force=True)
            run = load_run(run_dir)
            scores = evaluate(run, data, progress=False)["reconstruction"]
            seconds = run.record.log[-1]["seconds"]
            error_map(run_dir, scene, args.out / f"{name}-{space}-errors.png")
            results[f"{name}/{space}"] = {"floor": floor, "test": scores, "seconds": seconds}
            print(f"{name} {space:>9}: test PSNR {scores['psnr']:.2f} dB "
                  f"({floor['psnr'] - scores['psnr']:.2f} dB under the floor), SSIM "
                  f"{scores['ssim']:.3f}, trained in {seconds:.0f} s", flush=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    sys.exit(main())
