"""Weight NeRFs on the simulated scenes: what accuracy costs in time (PaletteNeRF's tables).

Each scene is simulated once (``nerf-stage simulate``); ``still-life`` gets additive
weights from ``palette-decompose -k 6`` on its training views, ``cornell-box`` its
order-2 transport weights. Then, on the test views:

1. RGB NeRF against the weight NeRF (RGB through the weights), per scene, at the
   same number of iterations (PSNR, SSIM, training time).
2. ``two-stage`` against ``traditional`` at an equal iteration budget.
3. The last-layer width 128 / 256 / 512 (``two-stage``, ``still-life``).
4. ``grid`` against ``mlp``: seconds per iteration and per rendered frame, and PSNR
   with the ``mlp`` given the ``grid``'s training time.
5. Cornell box: the weight render recoloured with an edited palette against the
   scene re-simulated with it, and recolouring against rendering time.
6. PSNR against training time: the training batches' PSNR over the seconds of
   each run, with the test PSNR at the end (figure ``nerf_psnr_time.png``).
7. Baked rendering (``render --baked FACTOR``) against the network's, per scene
   (``two-stage``, per-sample diffuse colours, the runs that bake), beside the default
   deferred head: baking time, seconds and frames per second, test PSNR.
8. The colour part per scene (``two-stage``): the paper's per-sample diffuse colours
   (one hidden layer), a deferred view-dependent head of one hidden layer, and the
   default of two.

Tables 1 to 3 print the paper's numbers beside ours (``PAPER``, ``PAPER_WIDTHS``).

    python benchmarks/bench_nerf.py [--out benchmarks/out/nerf] [--iters P F] [--lr-decay D]
                                    [--quick]

Runs are cached in OUT/runs: a finished run with the same config is evaluated again,
not retrained.
"""

from __future__ import annotations

import argparse
import time
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from bench_scenes import Snapshots
from bench_simulate import EDITED
from results import table, write_result

from nerf_stage.cli import main as nerf_stage
from nerf_stage.data.dataset import load_dataset
from nerf_stage.edit.evaluation import evaluate
from nerf_stage.train.checkpoint import CHECKPOINT
from nerf_stage.train.config import BAKE_FACTOR, TrainConfig
from nerf_stage.train.loading import load_run
from nerf_stage.train.run import CONFIG
from nerf_stage.train.trainer import train
from palette_core.basis import Basis
from palette_core.cli.decompose import main as decompose
from palette_core.stack import read_stack

SCENES = ("still-life", "cornell-box")
BAKE_FACTORS = range(2, BAKE_FACTOR + 1)  # up to the default
#: The colour parts set side by side: label, run, whether it bakes.
COLOUR_PARTS = (("per sample, diffuse, 1 layer (paper)", "two-stage per-sample", "yes"),
                ("deferred, view-dependent, 1 layer", "two-stage one-layer", "no"),
                ("deferred, view-dependent, 2 layers (default)", "two-stage", "no"))

#: Test PSNR / SSIM of PaletteNeRF (Q. Wu et al. 2022) beside ours. The still life stands
#: beside the paper's additive scenes (Table 1: the average of six captured scenes; its NeRF:
#: the average of the same six in Table 3), the Cornell box beside its Cornell box (Table 3;
#: traditional: Table 1's average of the Cornell box and breakfast).
PAPER = {
    "still-life": {"rgb": (27.293, 0.837), "two-stage": (26.711, 0.833),
                   "traditional": (25.205, 0.832)},
    "cornell-box": {"rgb": (44.151, 0.993), "two-stage": (41.339, 0.985),
                    "traditional": (8.579, 0.084)},
}
#: Table 2: PSNR of PaletteNeRF by last-layer width on vasedeck and lego.
PAPER_WIDTHS = {128: (24.262, 30.297), 256: (24.730, 30.525), 512: (24.732, 30.664)}


def prepare(scene: str, data: Path) -> tuple[Path, Path]:
    """Simulate ``scene`` (once) and return its dataset folder and weight stack: its
    transport weights, or, for a scene without editable materials, ``palette-decompose -k 6``
    of its training views."""
    root = data / scene
    if not (root / "transforms_test.json").is_file():
        assert nerf_stage(["simulate", scene, str(root), "--force"]) == 0
    if (root / "weights.npz").is_file():
        return root, root / "weights.npz"
    stack = data / f"{scene}-k6.npz"
    if not stack.is_file():
        assert decompose([str(root / "train"), "-k", "6", "-o", str(stack)]) == 0
    return root, stack


def scene_run(scene: str, out: Path, config: TrainConfig, snapshots: Path | None = None):
    """The built-in ``scene`` simulated into ``out`` (``prepare``) and its run,
    ``out/<scene>-run`` (``<scene>-<backbone>-run`` for another backbone than the grid),
    trained with ``config`` unless it is there already, its checkpoints kept in
    ``snapshots`` while it trains when given (``bench_scenes.Snapshots``); returns the
    dataset, the run and the weight stack's path."""
    root, stack_path = prepare(scene, out)
    dataset = load_dataset(root, config.background)
    backbone = "" if config.backbone == "grid" else f"-{config.backbone}"
    rundir = out / f"{scene}{backbone}-run"
    if not (rundir / CHECKPOINT).is_file():
        with Snapshots(rundir / CHECKPOINT, snapshots) if snapshots else nullcontext():
            train(config, dataset, read_stack(stack_path), rundir, force=True,
                  weights_path=str(stack_path.resolve()))
    return dataset, load_run(rundir), stack_path


def trained_run(name: str, config: TrainConfig, root: Path, stack: Path, runs: Path,
                scored: bool = True):
    """Train (or reuse) one run and, if ``scored``, evaluate it; returns its scores (if
    any), times and log."""
    rundir = runs / name
    done = (rundir / CHECKPOINT).is_file() and (rundir / CONFIG).is_file() and \
        TrainConfig.load(rundir / CONFIG).trains_like(config)
    dataset = load_dataset(root, config.background)
    if done and load_run(rundir, "cpu").record.iteration == config.total_iters:
        run = load_run(rundir)
    else:
        run = train(config, dataset, read_stack(stack), rundir, resume=done, force=not done,
                    weights_path=str(stack.resolve()))
    log = run.record.log
    edit = EDITED if run.basis == Basis.TRANSPORT else None
    scores = evaluate(run, dataset, edit, progress=False) if scored else {}
    scores.update(name=name, seconds=log[-1]["seconds"], iterations=len(log),
                  seconds_per_iter=log[-1]["seconds"] / len(log))
    scores["curve"] = [(e["seconds"], e["psnr"]) for e in log]
    psnr = f"PSNR {scores['reconstruction']['psnr']:.2f} dB" if scored else "trained"
    print(f"  {name}: {psnr} in {scores['seconds']:.0f} s", flush=True)
    return scores


def baked_table(scene: str, runs: dict, rundir: Path, root: Path) -> dict:
    """The per-sample network's render against the run baked at each of ``BAKE_FACTORS``,
    and the default deferred head's render."""
    run = load_run(rundir)
    dataset = load_dataset(root, run.config.background)
    network = runs["two-stage per-sample"]
    rows = [[f"{label} network", "", s["seconds_per_view"], 1 / s["seconds_per_view"], *rec(s),
             rec(s)[0] - rec(network)[0]]
            for label, s in (("deferred (default)", runs["two-stage"]), ("per-sample", network))]
    for factor in BAKE_FACTORS:
        start = time.perf_counter()
        baked = run.baked(factor)
        seconds = time.perf_counter() - start
        s = evaluate(baked, dataset, progress=False)
        rows.append([f"baked x{factor}", seconds, s["seconds_per_view"],
                     1 / s["seconds_per_view"], *rec(s), rec(s)[0] - rec(network)[0]])
    size = f"{dataset.intrinsics.width}x{dataset.intrinsics.height}"
    return table(f"{scene}: baked rendering against the network (two-stage, per-sample "
                 f"diffuse colours; {size} views)",
                 ["render", "bake s", "s / frame", "frames / s", "test PSNR", "test SSIM",
                  "PSNR - network"], rows)


def rec(s: dict) -> tuple[float, float]:
    return s["reconstruction"]["psnr"], s["reconstruction"]["ssim"]


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6 * len(results), 4), squeeze=False)
    for ax, (scene, runs) in zip(axes[0], results.items()):
        for s in runs.values():
            seconds, psnr = np.array(s["curve"]).T
            window = max(1, len(psnr) // 50)
            smooth = np.convolve(psnr, np.ones(window) / window, mode="valid")
            line, = ax.plot(seconds[window - 1:], smooth, label=s["name"], lw=1)
            ax.plot(seconds[-1], rec(s)[0], "o", color=line.get_color())
        ax.set(title=f"{scene}: training-batch PSNR (line), test PSNR (dot)",
               xlabel="training seconds", ylabel="PSNR (dB)")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"\nwrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/nerf"))
    parser.add_argument("--iters", type=int, nargs=2, default=None, metavar=("P", "F"),
                        help="pretrain and fine-tune iterations (default: TrainConfig's)")
    parser.add_argument("--lr-decay", type=float, default=TrainConfig.lr_decay,
                        help="learning-rate decay over each stage (default: TrainConfig's)")
    parser.add_argument("--quick", action="store_true", help="a few iterations, to check")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    args = parser.parse_args()
    p, f = args.iters or ((40, 20) if args.quick else (TrainConfig.pretrain_iters,
                                                        TrainConfig.finetune_iters))
    device = "cuda" if torch.cuda.is_available() else "cpu"
    print(f"device: {device} ({torch.cuda.get_device_name() if device == 'cuda' else 'CPU'}, "
          f"{torch.get_num_threads()} threads); P = {p}, F = {f}, lr decay {args.lr_decay}")
    base = TrainConfig(backbone="grid", pretrain_iters=p, finetune_iters=f,
                       lr_decay=args.lr_decay)
    results = {scene: scene_runs(scene, base, args.out) for scene in args.scenes}
    made = paper_tables(results, base)
    made += [baked_table(scene, runs, args.out / "runs" / scene / "two-stage per-sample",
                         args.out / "data" / scene) for scene, runs in results.items()]
    args.out.mkdir(parents=True, exist_ok=True)
    plot(results, args.out / "nerf_psnr_time.png")
    write_result("nerf", f"Weight NeRFs on the simulated scenes ({p} + {f} iterations)", made,
                 {sc: {n: {k: v for k, v in s.items() if k != "curve"} for n, s in r.items()}
                  for sc, r in results.items()})


def scene_runs(scene: str, base: TrainConfig, out: Path) -> dict[str, dict]:
    """Every configuration of the tables trained (or reused) on ``scene`` and scored."""
    print(f"\n{scene}:", flush=True)
    root, stack = prepare(scene, out / "data")
    runs = out / "runs" / scene
    one_layer = replace(base.grid, head_layers=1)
    configs = {
        "rgb": replace(base, strategy="rgb"),
        "two-stage": base,
        "traditional": replace(base, strategy="traditional"),
        "two-stage per-sample": replace(base, grid=replace(
            one_layer, deferred=False, view_frequencies=None)),
        "two-stage one-layer": replace(base, grid=one_layer),
    }
    if scene == "still-life":
        configs |= {f"two-stage w{w}": replace(base, head_width=w) for w in (256, 512)}
    scored = {name: trained_run(name, c, root, stack, runs) for name, c in configs.items()}
    if scene == "still-life":  # the mlp gets the grid's training time
        probe = trained_run("mlp probe", replace(base, backbone="mlp", pretrain_iters=4,
                                                 finetune_iters=2), root, stack, runs,
                            scored=False)
        total = max(3, int(scored["two-stage"]["seconds"] / probe["seconds_per_iter"]))
        p, f = base.pretrain_iters, base.finetune_iters
        mlp = replace(base, backbone="mlp", pretrain_iters=total * p // (p + f),
                      finetune_iters=total - total * p // (p + f))
        scored["mlp two-stage"] = trained_run("mlp two-stage", mlp, root, stack, runs)
    return scored


def paper_tables(results: dict[str, dict], base: TrainConfig) -> list[dict]:
    """Tables 1 to 3 of the paper beside ours, the edit and the colour part."""
    iterations = base.pretrain_iters + base.finetune_iters
    made = [table(f"{scene}: RGB NeRF against the weight NeRF, two-stage against traditional "
                  f"({iterations} iterations each)",
                  ["run", "test PSNR (dB)", "test SSIM", "training s", "s / iteration",
                   "paper PSNR", "paper SSIM"],
                  [[s["name"], *rec(s), s["seconds"], s["seconds_per_iter"],
                    *PAPER[scene][name]] for name, s in runs.items() if name in PAPER[scene]])
            for scene, runs in results.items()]
    if "still-life" in results:
        runs = results["still-life"]
        made.append(table("still-life: last-layer width (two-stage)",
                          ["width", "test PSNR", "test SSIM", "s / frame",
                           "paper vasedeck PSNR", "paper lego PSNR"],
                          [[w, *rec(runs[n]), runs[n]["seconds_per_view"], *PAPER_WIDTHS[w]]
                           for w, n in ((128, "two-stage"), (256, "two-stage w256"),
                                        (512, "two-stage w512"))]))
        made.append(table("still-life: grid against mlp at equal training time",
                          ["backbone", "iterations", "training s", "s / iteration",
                           "s / frame", "test PSNR"],
                          [[n.split()[0] if n != "two-stage" else "grid",
                            runs[n]["iterations"], runs[n]["seconds"],
                            runs[n]["seconds_per_iter"], runs[n]["seconds_per_view"],
                            rec(runs[n])[0]] for n in ("two-stage", "mlp two-stage")]))
    if "cornell-box" in results:
        s = results["cornell-box"]["two-stage"]
        made.append(table("cornell-box: edited palette against the re-simulated edit, "
                          "recolouring speed",
                          ["edit PSNR", "edit SSIM", "render s / frame", "recolour s / frame",
                           "speed-up"],
                          [[s["edit"]["psnr"], s["edit"]["ssim"], s["seconds_per_view"],
                            s["recolour_seconds_per_view"],
                            f"{s['seconds_per_view'] / s['recolour_seconds_per_view']:.0f}x"]]))
    made += [table(f"{scene}: the colour part (two-stage; view-dependent heads see "
                   f"{base.grid.view_frequencies} frequencies of the view direction)",
                   ["colour part", "test PSNR", "test SSIM", "edit PSNR", "training s",
                    "s / frame", "bakes"],
                   [[head, *rec(runs[n]), runs[n].get("edit", {}).get("psnr", ""),
                     runs[n]["seconds"], runs[n]["seconds_per_view"], bakes]
                    for head, n, bakes in COLOUR_PARTS])
             for scene, runs in results.items()]
    return made


if __name__ == "__main__":
    start = time.perf_counter()
    main()
    print(f"total {time.perf_counter() - start:.0f} s")
