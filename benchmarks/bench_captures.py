"""Real photo captures: held-out PSNR and SSIM of our palette NeRF (two-stage), our RGB
NeRF (``--strategy rgb``, the paper's Table 3 baseline) and nerfstudio's nerfacto, each
trained for the same wall-clock budget on the same photos, poses and held-out views, with
the peak memory of our training and a picture per capture and method.

The captures are folders in ROOT, one per name, that you fill once with the search tool's
``fetch`` (no program of ours downloads anything; none of them is committed):

- ``fox``: NVlabs/instant-ngp ``data/nerf/fox`` (phone photos of a fox figure, with
  ``transforms.json``: poses and ``k1 k2 p1 p2``);
- ``lund``: mapillary/OpenSfM ``data/lund/images`` (29 photos walking down a street);
- ``sceaux``: openMVG/ImageDataset_SceauxCastle ``images`` (11 photos of a castle front);
- ``monstree``: alicevision/dataset_monstree ``full`` (photos around a tree; the mirror
  holds 23 of its 41).

A folder with a ``transforms.json`` is posed; a folder of photos gets its poses from
``nerf-stage poses``. Each capture is then written again at 1/``--downscale`` of its size,
undistorted, as PNGs in nerfstudio's layout with every eighth photo held out in its
``test_filenames`` (``OUT/NAME/data``): both NeRF codes read those same pixels, poses and
splits. ``palette-decompose -k 6`` makes the weight stack of its photos.

Budget: each method trains for ``--minutes``. Ours: a short probe run measures the seconds
an iteration takes, and the pretrain and fine-tune iterations (in the defaults' ratio) are
set to fill the budget. nerfacto (PyTorch implementation, ``--machine.device-type cpu``
without CUDA) runs in its own virtual environment, ``--nerfacto-venv``, which this script
creates when missing (PyPI's ``nerfstudio``; never a dependency of ours); it trains with
``--max-num-iterations`` set the same way from its own probe. Its held-out views are
rendered by ``ns-eval`` into PNGs and scored here, by the same ``image_scores`` as ours.

    python benchmarks/bench_captures.py ROOT [--out benchmarks/out/captures]
        [--captures fox lund sceaux monstree] [--minutes 20] [--downscale 4]
        [--methods palette rgb nerfacto] [--nerfacto-venv benchmarks/out/nerfacto-venv]

Writes ``OUT/results.json`` and ``OUT/NAME-METHOD.png`` (held-out views: truth | render |
absolute error x4). Runs are cached in OUT by capture and method.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from bench_scenes import error_map, rendered
from PIL import Image

from nerf_stage.data import load_dataset
from nerf_stage.metrics import image_scores
from nerf_stage.run import load_run

CAPTURES = ("fox", "lund", "sceaux", "monstree")
METHODS = ("palette", "rgb", "nerfacto")
PROBE_ITERS = 20  # iterations of the probe that times a method
BIN = Path(sys.executable).parent
NERFSTUDIO = ("torch==2.14.1", "torchvision==0.29.1", "nerfstudio")
#: nerfacto's model builds an LPIPS metric whose AlexNet weights torchvision downloads; with
#: no network here its venv gets this ``sitecustomize.py``, an LPIPS that returns NaN (a
#: metric only: training and the renders are nerfacto's own).
NO_LPIPS = """import torch
import torchmetrics.image.lpip as lpip


class NoLPIPS(torch.nn.Module):
    def forward(self, a, b):
        return torch.tensor(float("nan"))


lpip.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: NoLPIPS()
"""


def posed(source: Path, out: Path) -> Path:
    """``source`` if it holds a ``transforms.json``, else its photos posed into ``out``."""
    if (source / "transforms.json").is_file():
        return source
    if not (out / "transforms.json").is_file():
        _run([BIN / "nerf-stage", "poses", source, "-o", out, "--force"], "poses")
    return out


def small_capture(capture: Path, out: Path, downscale: int) -> Path:
    """``capture`` at 1/``downscale`` of its size, undistorted, in PNGs with its splits
    named in ``transforms.json`` (written once), and its weight stack."""
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
        (out / "transforms.json").write_text(json.dumps({
            "camera_model": "PINHOLE", "w": data.intrinsics.width, "h": data.intrinsics.height,
            "frames": frames, "train_filenames": splits["train"],
            "val_filenames": splits["test"], "test_filenames": splits["test"]}, indent=1))
        _run([BIN / "palette-decompose", out / "images", "-k", "6", "-o", out / "weights.npz"],
             "decompose")
    return out


def ours(data_dir: Path, run_dir: Path, strategy: str, seconds: float) -> dict:
    """Train our NeRF on ``data_dir`` for about ``seconds``; its scores, renders, iterations,
    training seconds and peak memory."""
    if not (run_dir / "checkpoint.pt").is_file():
        probe = run_dir.with_name(run_dir.name + "-probe")
        _train(data_dir, probe, strategy, PROBE_ITERS, PROBE_ITERS)
        log = load_run(probe).record.log
        per_iter = (log[-1]["seconds"] - log[0]["seconds"]) / (len(log) - 1)
        total = max(2, int(seconds / per_iter))
        pretrain = round(total * 4200 / 7200)
        output = _train(data_dir, run_dir, strategy, pretrain, total - pretrain)
        (run_dir / "train.log").write_text(output)
        shutil.rmtree(probe)
    run, data = load_run(run_dir), load_dataset(data_dir)
    ids = data.indices("test")
    render = rendered(run, data, ids)
    memory = re.search(r"peak memory ([\d.]+) GB", (run_dir / "train.log").read_text())
    return {"render": render, "iterations": run.record.iteration,
            "seconds": run.record.log[-1]["seconds"],
            "peak_gb": float(memory.group(1)) if memory else None}


def _train(data_dir: Path, run_dir: Path, strategy: str, pretrain: int, finetune: int) -> str:
    return _run([BIN / "nerf-stage", "train", data_dir, "-o", run_dir, "--force",
                 "--strategy", strategy, "--pretrain-iters", str(pretrain),
                 "--finetune-iters", str(finetune)], f"train {strategy}")


def nerfacto_venv(venv: Path) -> Path:
    """The ``bin`` folder of a virtual environment with nerfstudio, created when missing."""
    if not (venv / "bin" / "ns-train").is_file():
        subprocess.run([sys.executable, "-m", "venv", venv], check=True)
        for package in (NERFSTUDIO[:2], NERFSTUDIO[2:]):  # torch first, as pinned
            subprocess.run([venv / "bin" / "pip", "install", "-q", *package], check=True)
    site = next(venv.glob("lib/python*/site-packages"))
    if not (site / "sitecustomize.py").is_file():
        (site / "sitecustomize.py").write_text(NO_LPIPS)
    return venv / "bin"


def nerfacto(data_dir: Path, run_dir: Path, seconds: float, venv: Path) -> dict:
    """Train nerfacto on ``data_dir`` for about ``seconds`` (its iterations timed by a
    probe run); its renders of the held-out views, iterations and training seconds."""
    bin_dir, renders = nerfacto_venv(venv), run_dir / "renders"
    if not (run_dir / "result.json").is_file():
        per_iter = _nerfacto_train(bin_dir, data_dir, run_dir / "probe", PROBE_ITERS)[1]
        iterations = max(2, int(seconds / per_iter))
        config, per_iter = _nerfacto_train(bin_dir, data_dir, run_dir / "train", iterations)
        shutil.rmtree(renders, ignore_errors=True)
        _run([bin_dir / "ns-eval", "--load-config", config, "--output-path",
              run_dir / "eval.json", "--render-output-path", renders], "ns-eval")
        (run_dir / "result.json").write_text(json.dumps(
            {"iterations": iterations, "seconds": iterations * per_iter}))
    result = json.loads((run_dir / "result.json").read_text())
    images = sorted(renders.glob("*-rgb.png")) or sorted(renders.glob("*rgb*"))
    result["render"] = np.stack([np.asarray(Image.open(p).convert("RGB"), np.float32) / 255
                                 for p in images])
    return result


def _nerfacto_train(bin_dir: Path, data_dir: Path, out: Path, iterations: int):
    """Run ``ns-train nerfacto`` for ``iterations``; its config file and seconds an
    iteration (the training loop's, from its own timing, without start-up)."""
    device = [] if _has_cuda(bin_dir) else ["--machine.device-type", "cpu",
                                            "--pipeline.model.implementation", "torch"]
    start = time.perf_counter()
    output = _run([bin_dir / "ns-train", "nerfacto", "--output-dir", out,
                   "--max-num-iterations", str(iterations), "--vis", "tensorboard",
                   "--steps-per-save", str(iterations), "--viewer.quit-on-train-completion",
                   "True", *device, "nerfstudio-data", "--data", data_dir,
                   "--downscale-factor", "1"], "ns-train")
    wall = time.perf_counter() - start
    config = sorted(out.rglob("config.yml"))[-1]
    stamps = sorted(p.stat().st_mtime for p in config.parent.rglob("*.ckpt"))
    began = config.stat().st_mtime
    seconds = (stamps[-1] - began) if stamps else wall
    del output
    return config, seconds / iterations


def _has_cuda(bin_dir: Path) -> bool:
    probe = subprocess.run([bin_dir / "python", "-c",
                            "import torch; print(torch.cuda.is_available())"],
                           capture_output=True, text=True)
    return probe.stdout.strip() == "True"


def _run(command: list, what: str) -> str:
    """Run ``command``; its output (stderr too), or exit with its last lines."""
    done = subprocess.run([str(c) for c in command], capture_output=True, text=True,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})
    if done.returncode:
        sys.exit(f"{what} failed:\n" + "\n".join((done.stdout + done.stderr)
                                                   .splitlines()[-15:]))
    return done.stdout + done.stderr


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("root", type=Path, help="folder of captures, one folder per name")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/captures"))
    parser.add_argument("--captures", nargs="+", default=list(CAPTURES))
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--minutes", type=float, default=20.0)
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--nerfacto-venv", type=Path,
                        default=Path("benchmarks/out/nerfacto-venv"))
    args = parser.parse_args()
    results_path = args.out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {}
    for name in args.captures:
        folder = args.out / name
        capture = posed(args.root / name, folder / "posed")
        data_dir = small_capture(capture, folder / "data", args.downscale)
        data = load_dataset(data_dir)
        truth = data.images[data.indices("test")]
        for method in args.methods:
            run_dir, seconds = folder / method, 60 * args.minutes
            if method == "nerfacto":
                result = nerfacto(data_dir, run_dir, seconds, args.nerfacto_venv.resolve())
            else:
                result = ours(data_dir, run_dir, "two-stage" if method == "palette" else "rgb",
                              seconds)
            render = result.pop("render")
            result.update(image_scores(render, truth), views=len(truth),
                          size=f"{data.intrinsics.width}x{data.intrinsics.height}",
                          train_views=len(data.indices("train")))
            error_map(truth, render, args.out / f"{name}-{method}.png")
            results.setdefault(name, {})[method] = result
            print(f"{name} {method}: PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f} "
                  f"on {len(truth)} held-out views at {result['size']}; "
                  f"{result['iterations']} iterations in {result['seconds']:.0f} s"
                  + (f", peak {result['peak_gb']:.2f} GB" if result.get("peak_gb") else ""),
                  flush=True)
            args.out.mkdir(parents=True, exist_ok=True)
            results_path.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
