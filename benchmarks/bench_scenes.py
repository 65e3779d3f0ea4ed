"""Weight NeRFs on scenes rendered by Blender's Cycles (``benchmarks/scenes/``), not by our
path tracer: PSNR and SSIM of held-out views on the training path (``val``) and off it
(``test``) against each scene's noise floor, per scene space and strategy.

For each scene: render it (once; ``blender -b --factory-startup -P SCRIPT -- DIR``), measure
the noise floor (the held-out views against the same views rendered under another sampler
seed, ``val_seed2/`` and ``test_seed2/``), decompose its training views (``palette-decompose
-k 6``), then train per ``--backbones`` x ``--spaces`` x ``--strategies`` and score the held-out
views, saving an error map of each run's first test views
(``OUT/SCENE-SPACE-STRATEGY[-BACKBONE].png``: truth, render, absolute error x4) and of its
first views on the training path (``...-val.png``). With
``--curve-points N``, about N checkpoints of each run are kept while it trains and scored on
the test views: ``OUT/SCENE-curve.png``, test PSNR against training time for every run of
the scene.

    python benchmarks/bench_scenes.py [--out benchmarks/out/scenes] [--scenes garden ...]
        [--backbones grid splats] [--minutes 4] [--spaces auto]
        [--strategies two-stage rgb] [--iters P F] [--curve-points 10]

Needs Debian's ``blender`` (or PyPI's ``bpy``); runs are cached in OUT by scene, space, strategy
and backbone (delete a run folder to train it again).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import itertools
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from PIL import Image
from results import table, write_result

from nerf_stage.backbones import BACKBONES
from nerf_stage.data.dataset import load_dataset
from nerf_stage.edit.editing import WeightRender
from nerf_stage.fields import RGB
from nerf_stage.train.config import TrainConfig
from nerf_stage.train.loading import load_run
from nerf_stage.train.metrics import image_scores
from nerf_stage.train.trainer import train
from palette_core import decompose, read_stack

SCENES = Path(__file__).parent / "scenes"
SPLITS = ("val", "test")


def render_scene(name: str, out: Path, resolution: int = 100, spp: int = 64) -> Path:
    """``OUT/NAME`` (``NAME-RESpx-SPPspp`` at other settings): the scene rendered once and
    its training views decomposed."""
    scene = out / (name if (resolution, spp) == (100, 64) else f"{name}-{resolution}px-{spp}spp")
    if not (scene / "transforms_test.json").exists():
        start = time.perf_counter()
        subprocess.run(["blender", "-b", "--factory-startup", "-P", str(SCENES / f"{name}.py"),
                        "--", str(scene), "--resolution", str(resolution), "--spp", str(spp)],
                       check=True, stdout=subprocess.DEVNULL)
        print(f"{name}: rendered in {time.perf_counter() - start:.0f} s", flush=True)
    if not (scene / "weights.npz").exists():
        decompose([scene / "train"], k=6).write(scene / "weights.npz")
    return scene


def exposed(scene: Path, sigma: float) -> Path:
    """A copy of ``scene`` whose training photos each have their own exposure and white
    balance, as a hand-held camera's do: gains exp(N(0, sigma)), one for the image times
    one per channel (seeded); the held-out views as rendered. Decomposed anew."""
    out = scene.with_name(f"{scene.name}-exposure{sigma:g}")
    if not (out / "weights.npz").exists():
        shutil.copytree(scene, out, dirs_exist_ok=True, symlinks=True,  # links stay links
                        ignore=shutil.ignore_patterns("weights*"))
        rng = np.random.default_rng(0)
        for png in sorted((out / "train").glob("*.png")):
            rgba = np.asarray(Image.open(png).convert("RGBA"), np.float64)
            gains = np.exp(rng.normal(0, sigma) + rng.normal(0, sigma, 3))
            rgba[..., :3] = np.clip(rgba[..., :3] * gains, 0, 255)
            Image.fromarray(rgba.round().astype(np.uint8)).save(png)
        decompose([out / "train"], k=6).write(out / "weights.npz")
    return out


def noise_floor(data, split: str) -> dict:
    """Scores of a split's views against their renders under another sampler seed."""
    ids = data.indices(split)
    again = [Image.open(data.root / f"{split}_seed2" / Path(data.names[i]).name) for i in ids]
    rgba = np.stack([np.asarray(im.convert("RGBA"), np.float32) / 255 for im in again])
    rgb = rgba[..., :3] * rgba[..., 3:] + (1 - rgba[..., 3:]) * data.background
    return image_scores(rgb, data.images[ids])


def rendered(run, data, ids) -> np.ndarray:
    """(N, H, W, 3) colours of the run at the dataset's views ``ids`` (through the weights)."""
    values, opacity = run.render(data.poses[ids])
    background = np.asarray(run.config.background)
    if run.kind == RGB:
        return np.clip(values + (1 - opacity[..., None]) * background, 0, 1)
    return WeightRender(values, opacity, [data.names[i] for i in ids], run.palette, run.basis,
                        run.order, background, {}).recolor()


def error_map(truth: np.ndarray, render: np.ndarray, path: Path, views: int = 3,
              seen: np.ndarray | None = None) -> None:
    """The first ``views`` views a row each: truth | render | absolute error x 4, and with
    (N, H, W) ``seen`` counts, how many training views see each pixel's surface (black:
    none, white: four or more)."""
    rows = []
    for n, (t, r) in enumerate(zip(truth[:views], render[:views])):
        panels = [t, r, np.clip(4 * np.abs(r - t), 0, 1)]
        if seen is not None:
            panels.append(np.repeat(np.clip(seen[n] / 4, 0, 1)[..., None], 3, axis=2))
        rows.append(np.concatenate(panels, 1))
    picture = (np.concatenate(rows, 0) * 255).round().astype(np.uint8)
    Image.fromarray(picture).resize((picture.shape[1] * 2, picture.shape[0] * 2),
                                    Image.NEAREST).save(path)


class Snapshots(threading.Thread):
    """While in its ``with``, keeps each new version of ``checkpoint`` that a training
    process writes (atomically, by renaming) as a hard link in ``folder``, emptied first
    (the version there before, an earlier run's, is not kept)."""

    def __init__(self, checkpoint: Path, folder: Path):
        super().__init__(daemon=True)
        self.checkpoint, self.folder, self.done = checkpoint, folder, threading.Event()
        self.seen = None

    def __enter__(self):
        self.folder.mkdir(parents=True, exist_ok=True)
        for old in self.folder.glob("*.pt"):
            old.unlink()
        if self.checkpoint.is_file():
            self.seen = _version(self.checkpoint)
        self.start()
        return self

    def __exit__(self, *exc):
        self.done.set()
        self.join()

    def run(self) -> None:
        while True:
            finished = self.done.is_set()  # one last look after the process has ended
            try:
                version = _version(self.checkpoint)
                if version != self.seen:
                    os.link(self.checkpoint, self.folder / f"{time.monotonic_ns()}.pt")
                    self.seen = version
            except FileNotFoundError:  # not written yet, or renamed over just now
                pass
            if finished:
                return
            self.done.wait(0.5)


def _version(path: Path) -> tuple[int, int]:
    """What tells one written version of a file from the next: its inode and mtime."""
    status = path.stat()
    return status.st_ino, status.st_mtime_ns


def checkpoint_curve(snapshots: Path, data, ids) -> list[tuple[float, float]]:
    """(training seconds, PSNR of views ``ids`` of ``data``) of each checkpoint that
    ``Snapshots`` kept in ``snapshots``, in the order they were written."""
    curve = []
    for path in sorted(snapshots.glob("*.pt"), key=lambda path: int(path.stem)):
        with tempfile.TemporaryDirectory(dir=snapshots) as folder:
            os.link(path, Path(folder) / "checkpoint.pt")
            run = load_run(folder)
        scores = image_scores(rendered(run, data, ids), data.images[ids])
        curve.append((run.record.log[-1]["seconds"], scores["psnr"]))
    return curve


def curve_picture(methods: dict, title: str, path: Path) -> None:
    """Held-out PSNR against training seconds: a line per method with a ``curve``, a point
    for each with only its end (nerfacto)."""
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib import pyplot

    figure, axes = pyplot.subplots(figsize=(6, 4))
    for method, result in sorted(methods.items()):
        seconds, psnr = zip(*(result.get("curve") or [(result["seconds"], result["psnr"])]))
        axes.plot(np.divide(seconds, 60), psnr, "o-", label=method)
    axes.set(xlabel="training minutes", ylabel="held-out PSNR (dB)", title=title)
    axes.grid(alpha=0.3)
    axes.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    pyplot.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/scenes"))
    parser.add_argument("--scenes", nargs="+",
                        default=sorted(p.stem for p in SCENES.glob("[!_]*.py")))
    parser.add_argument("--backbones", nargs="+", default=["grid"], choices=BACKBONES)
    parser.add_argument("--minutes", type=float, default=0.0,
                        help="training time limit of each run (0: none)")
    parser.add_argument("--spaces", nargs="+", default=["auto"])
    parser.add_argument("--strategies", nargs="+", default=["two-stage", "rgb"])
    parser.add_argument("--iters", type=int, nargs=2, default=None, metavar=("P", "F"))
    parser.add_argument("--exposure", type=float, default=0.0, metavar="SIGMA",
                        help="train on photos re-exposed by gains exp(N(0, SIGMA)) (exposed)")
    parser.add_argument("--appearance", nargs="+", default=["off"], choices=("off", "on"),
                        help="train without and/or with per-image colour transforms")
    parser.add_argument("--curve-points", type=int, default=0,
                        help="checkpoints of each run scored on the test views for the "
                             "PSNR-against-time curve (0: the end alone)")
    args = parser.parse_args()
    results = {}
    for name in args.scenes:
        scene = render_scene(name, args.out)
        if args.exposure:
            scene, name = exposed(scene, args.exposure), f"{name}-exposure{args.exposure:g}"
        data, stack = load_dataset(scene), read_stack(scene / "weights.npz")
        floor = {split: noise_floor(data, split) for split in SPLITS}
        print(f"{name}: noise floor " + ", ".join(f"{s} {floor[s]['psnr']:.2f} dB"
                                                  for s in SPLITS), flush=True)
        curves = {}
        for backbone, space, strategy, appearance in itertools.product(
                args.backbones, args.spaces, args.strategies, args.appearance):
            iters = dict(zip(("pretrain_iters", "finetune_iters"), args.iters or ()))
            config = TrainConfig(backbone=backbone, space=space, strategy=strategy,
                                 appearance=appearance == "on", minutes=args.minutes, **iters)
            label = (f"{name}-{space}-{strategy}" + ("-appearance" * config.appearance)
                     + (f"-{backbone}" if backbone != "grid" else ""))
            run_dir = args.out / label
            snapshots = run_dir.with_name(label + "-snapshots")
            if not (run_dir / "checkpoint.pt").exists():
                if args.curve_points:
                    config = dataclasses.replace(config, checkpoint_every=max(
                        1, config.total_iters // args.curve_points))
                with (Snapshots(run_dir / "checkpoint.pt", snapshots) if args.curve_points
                      else contextlib.nullcontext()):
                    train(config, data, stack, run_dir, force=True)
            run = load_run(run_dir)
            scores = {}
            for split in SPLITS:
                ids = data.indices(split)
                render = rendered(run, data, ids)
                scores[split] = image_scores(render, data.images[ids])
                suffix = "" if split == "test" else f"-{split}"
                error_map(data.images[ids], render, args.out / f"{label}{suffix}.png")
            seconds = run.record.log[-1]["seconds"]
            curve = (checkpoint_curve(snapshots, data, data.indices("test"))
                     if args.curve_points else [])
            results[label] = {"floor": floor, "scores": scores, "seconds": seconds,
                              "unbounded": run.box.unbounded, "curve": curve}
            gaps = {s: floor[s]["psnr"] - scores[s]["psnr"] for s in SPLITS}
            print(f"{label} ({'unbounded' if run.box.unbounded else 'box'}): "
                  + ", ".join(f"{s} {scores[s]['psnr']:.2f} dB / SSIM "
                              f"{scores[s]['ssim']:.3f} ({gaps[s]:.2f} dB under the floor)"
                              for s in SPLITS)
                  + f", trained in {seconds:.0f} s", flush=True)
            curves[label[len(name) + 1:]] = {"curve": curve}
        if args.curve_points:
            curve_picture(curves, f"{name}, test views", args.out / f"{name}-curve.png")
    made = table("Held-out views against each scene's noise floor (PSNR dB / SSIM)",
                 ["run", "space", *(f"{s} (under the floor)" for s in SPLITS), "training s"],
                 [[label, "unbounded" if r["unbounded"] else "box",
                   *(f"{r['scores'][s]['psnr']:.2f} / {r['scores'][s]['ssim']:.3f} "
                     f"({r['floor'][s]['psnr'] - r['scores'][s]['psnr']:.2f})" for s in SPLITS),
                   round(r["seconds"])] for label, r in results.items()])
    write_result("scenes", "Scenes rendered by Blender's Cycles", [made], results)


if __name__ == "__main__":
    sys.exit(main())
