"""nerfstudio's nerfacto for ``bench_captures.py``: trained in its own virtual environment
(never a dependency of ours), stopped by the clock, its held-out views rendered by
``ns-eval``; and the one way the benchmarks run a command."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

NERFSTUDIO = ("torch==2.14.1", "torchvision==0.29.1", "nerfstudio")
#: What nerfacto's venv imports at every start, through a ``.pth`` file (a
#: ``sitecustomize.py`` would lose to a system one), as ``bench_hooks.py``:
#: - nerfacto's model builds an LPIPS metric whose AlexNet weights torchvision downloads;
#:   with no network here it gets one that returns NaN (a metric only);
#: - with ``BENCH_SECONDS`` set, ns-train's trainer saves its checkpoint and ends at the
#:   first iteration that starts after that many seconds of training, and says how many
#:   iterations it trained (``CLOCK_LINE``).
#: Training and the renders are nerfacto's own.
BENCH_HOOKS = """import os
import sys
import time

import torch
import torchmetrics.image.lpip as lpip


class NoLPIPS(torch.nn.Module):
    def forward(self, a, b):
        return torch.tensor(float("nan"))


lpip.LearnedPerceptualImagePatchSimilarity = lambda *args, **kwargs: NoLPIPS()

if os.environ.get("BENCH_SECONDS"):
    from nerfstudio.engine.trainer import Trainer

    budget, train_iteration = float(os.environ["BENCH_SECONDS"]), Trainer.train_iteration

    def clocked(self, step):
        if not hasattr(self, "bench_start"):
            self.bench_start, self.bench_first = time.perf_counter(), step
        elapsed = time.perf_counter() - self.bench_start
        if elapsed >= budget:
            self.save_checkpoint(step - 1)
            print(f"bench clock: {step - self.bench_first} iterations in {elapsed:.3f} s",
                  flush=True)
            sys.exit(0)
        return train_iteration(self, step)

    Trainer.train_iteration = clocked
"""
CLOCK_LINE = re.compile(r"bench clock: (\d+) iterations in ([\d.]+) s")


def nerfacto_venv(venv: Path) -> Path:
    """The ``bin`` folder of a virtual environment with nerfstudio, created when missing."""
    if not (venv / "bin" / "ns-train").is_file():
        subprocess.run([sys.executable, "-m", "venv", venv], check=True)
        for package in (NERFSTUDIO[:2], NERFSTUDIO[2:]):  # torch first, as pinned
            subprocess.run([venv / "bin" / "pip", "install", "-q", *package], check=True)
    site = next(venv.glob("lib/python*/site-packages"))
    (site / "bench_hooks.py").write_text(BENCH_HOOKS)
    (site / "bench_hooks.pth").write_text("import bench_hooks\n")
    return venv / "bin"


def nerfacto(data_dir: Path, run_dir: Path, seconds: float, venv: Path) -> dict:
    """Train nerfacto on ``data_dir`` for ``seconds`` of training (``BENCH_HOOKS``); its
    renders of the held-out views, iterations and training seconds."""
    bin_dir = nerfacto_venv(venv)
    if not (run_dir / "result.json").is_file():
        run_dir.mkdir(parents=True, exist_ok=True)
        config, iterations, trained = _nerfacto_train(bin_dir, data_dir, run_dir / "train",
                                                      seconds, run_dir / "train.log")
        renders = config.parent / "renders"  # beside the config ns-train just made
        run_command([bin_dir / "ns-eval", "--load-config", config, "--output-path",
              run_dir / "eval.json", "--render-output-path", renders], "ns-eval",
             TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD="1")  # its own checkpoint, pickled by torch<2.6
        (run_dir / "result.json").write_text(json.dumps(
            {"iterations": iterations, "seconds": trained, "renders": str(renders)}))
    result = json.loads((run_dir / "result.json").read_text())
    pairs = [np.asarray(Image.open(p).convert("RGB"), np.float32) / 255  # truth | render
             for p in sorted(Path(result.pop("renders")).glob("eval_img_*.png"))]
    result["render"] = np.stack([pair[:, pair.shape[1] // 2:] for pair in pairs])
    return result


def _nerfacto_train(bin_dir: Path, data_dir: Path, out: Path, seconds: float, log: Path):
    """Run ``ns-train nerfacto`` (its PyTorch implementation, on CUDA where its torch has
    it) for ``seconds`` of training, its output to ``log``; its config file, the iterations
    it trained and the seconds they took."""
    device = ["--pipeline.model.implementation", "torch"]
    if not _has_cuda(bin_dir):
        device += ["--machine.device-type", "cpu"]
    endless = str(10**8)  # the clock ends it (BENCH_HOOKS)
    output = run_command([bin_dir / "ns-train", "nerfacto", "--output-dir", out,
                   "--max-num-iterations", endless, "--steps-per-save", endless,
                   "--vis", "tensorboard", "--logging.local-writer.max-log-size", "0",
                   *device, "nerfstudio-data", "--data", data_dir, "--downscale-factor", "1"],
                  "ns-train", log, BENCH_SECONDS=str(seconds))
    clock = CLOCK_LINE.search(output)
    if not clock:
        sys.exit(f"ns-train did not stop by the clock:\n{output[-2000:]}")
    return sorted(out.rglob("config.yml"))[-1], int(clock.group(1)), float(clock.group(2))


def _has_cuda(bin_dir: Path) -> bool:
    probe = subprocess.run([bin_dir / "python", "-c",
                            "import torch; print(torch.cuda.is_available())"],
                           capture_output=True, text=True)
    return probe.stdout.strip() == "True"


def run_command(command: list, what: str, log: Path | None = None, **env: str) -> str:
    """Run ``command`` with ``env`` added, its output (stderr too) written to ``log`` while it
    runs (a temporary file without one, so that a run stopped from outside leaves it); that
    output, or exit with its last lines."""
    with tempfile.TemporaryFile("w+") if log is None else open(log, "w+") as file:
        done = subprocess.run([str(c) for c in command], stdout=file, stderr=subprocess.STDOUT,
                              env={**os.environ, "PYTHONUNBUFFERED": "1", **env})
        file.seek(0)
        output = file.read()
    if done.returncode:
        sys.exit(f"{what} failed:\n" + "\n".join(output.splitlines()[-15:]))
    return output
