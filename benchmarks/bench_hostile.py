"""What a crafted file makes a command allocate before it is refused (docs/security.md).

Crafted files of a few kilobytes declare up to twelve gigabytes: splat checkpoints whose
tensors are views repeating one row 10^3 to 10^9 times, a checkpoint whose zip directory
claims 4 GB for a member, a weight stack whose NPZ member lies about its size, a PNG header
of 20000 x 20000 pixels. Each is given to the command that reads it (``nerf-stage export``,
``palette-recolor``, ``palette-decompose``) in a child process; its peak resident memory
(``wait4``'s ``ru_maxrss``) is compared with a child that only imports what the command
imports. Target: what the file declares never moves the peak (a refusal costs the same for
10^3 rows as for 10^9), and no more than a small multiple of the file's size beyond the
command's own start.

    python benchmarks/bench_hostile.py [--work DIR]
"""

from __future__ import annotations

import argparse
import shutil
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from results import table, write_result

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from palette_core.stack import write_stack  # noqa: E402
from tests.hostile import lying_npz, small_stack  # noqa: E402
from tests.test_one_line import _huge_png  # noqa: E402

IMPORTS = ("import torch, numpy, PIL.Image, nerf_stage.cli, nerf_stage.train.loading, "
           "nerf_stage.splats, palette_core.cli.recolor, palette_core.cli.decompose")


def peak_mb(code: str) -> tuple[int, float]:
    """Exit code and peak resident MB of ``python -c code``: the process's own high-water
    mark (``VmHWM``, reset when it starts, unlike ``ru_maxrss``, which keeps this
    process's, forked, size)."""
    with tempfile.NamedTemporaryFile("r") as peak:
        wrapped = (f"import sys\ntry:\n    {code}\nfinally:\n    open({peak.name!r}, 'w').write("
                   "[l for l in open('/proc/self/status') if l.startswith('VmHWM')][0])")
        done = subprocess.run([sys.executable, "-c", wrapped], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, cwd=ROOT)
        return done.returncode, int(Path(peak.name).read_text().split()[1]) / 1024


def command(module: str, argv: list[str]) -> str:
    return f"from {module} import main; sys.exit(main({argv!r}))"


def splat_run(work: Path) -> Path:
    """A tiny splat run of a 16 x 16 still life."""
    run = work / "run"
    if (run / "checkpoint.pt").is_file():
        return run
    nerf = [sys.executable, "-m", "nerf_stage.cli"]
    subprocess.run([*nerf, "simulate", "still-life", str(work / "sl"), "--resolution", "16",
                    "--spp", "2", "--views", "4", "1", "1", "--force"], check=True,
                   capture_output=True, cwd=ROOT)
    subprocess.run([sys.executable, "-m", "palette_core.cli.decompose", str(work / "sl/train"),
                    "-k", "4", "-o", str(work / "sl/weights.npz"), "--force"], check=True,
                   capture_output=True, cwd=ROOT)
    subprocess.run([*nerf, "train", str(work / "sl"), "-o", str(run), "--backbone", "splats",
                    "--pretrain-iters", "4", "--finetune-iters", "2", "--splats-initial", "64",
                    "--force"], check=True, capture_output=True, cwd=ROOT)
    return run


def crafted(work: Path, run: Path) -> dict[str, tuple[Path, int, str]]:
    """Case -> (the file, the bytes it declares, the command reading it)."""
    cases = {}
    for rows in (10**3, 10**6, 10**9):
        folder = work / f"repeat-{rows}"
        shutil.copytree(run, folder, symlinks=True, dirs_exist_ok=True)
        state = torch.load(folder / "checkpoint.pt", weights_only=True)
        state["field"] = {k: v[:1].expand(rows, *v.shape[1:]) for k, v in state["field"].items()}
        declared = sum(v.numel() * v.element_size() for v in state["field"].values())
        torch.save(state, folder / "checkpoint.pt")
        cases[f"checkpoint, rows repeated to {rows:.0e}"] = (
            folder / "checkpoint.pt", declared,
            command("nerf_stage.cli", ["export", str(folder), "-o", str(work / "o.ply")]))
    folder = work / "zip-lies"
    shutil.copytree(run, folder, symlinks=True, dirs_exist_ok=True)
    data = bytearray((folder / "checkpoint.pt").read_bytes())
    entry = data.index(b"PK\x01\x02")
    data[entry + 24:entry + 28] = struct.pack("<I", 0xFFFFFFF0)
    (folder / "checkpoint.pt").write_bytes(bytes(data))
    cases["checkpoint, zip member claims 4 GB"] = (
        folder / "checkpoint.pt", 0xFFFFFFF0,
        command("nerf_stage.cli", ["export", str(folder), "-o", str(work / "o.ply")]))
    stack = work / "w.npz"
    write_stack(small_stack(np.random.default_rng(0)), stack)
    lying_npz(stack, work / "lying.npz", "weights")
    cases["weight stack, NPZ member declares 10^12 images"] = (
        work / "lying.npz", 10**12 * 6 * 5 * 4 * 4,
        command("palette_core.cli.recolor", [str(work / "lying.npz"), "-o", str(work / "r")]))
    (work / "photos").mkdir(exist_ok=True)
    _huge_png(work / "photos" / "huge.png")
    cases["PNG header of 20000 x 20000"] = (
        work / "photos" / "huge.png", 20000 * 20000 * 3,
        command("palette_core.cli.decompose", [str(work / "photos"), "-o",
                                                str(work / "d.npz")]))
    return cases


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--work", type=Path, default=None, help="folder for the crafted files")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        work = args.work or Path(scratch)
        work.mkdir(parents=True, exist_ok=True)
        cases = crafted(work, splat_run(work))
        _, base = peak_mb(IMPORTS)
        rows, results = [], {"imports_peak_mb": base, "cases": {}}
        for name, (path, declared, code) in cases.items():
            exit_code, peak = peak_mb(code)
            size = path.stat().st_size
            extra = max(peak - base, 0.0)
            results["cases"][name] = {"file_bytes": size, "declared_bytes": declared,
                                      "exit_code": exit_code, "peak_mb": peak,
                                      "above_imports_mb": extra}
            rows.append([name, size, f"{declared / 2**20:.3g}", exit_code, round(peak),
                         round(extra, 1)])
            print(f"{name:48} {size:>9} B file, declares {declared / 2**20:>10.3g} MB: exit "
                  f"{exit_code}, {extra:7.1f} MB above the imports' {base:.0f} MB", flush=True)
    made = table("memory before refusal", ["crafted file", "bytes", "declares (MB)", "exit",
                                           "peak (MB)", f"above the imports' {base:.0f} MB"],
                 rows)
    write_result("hostile", "Crafted files refused: memory before refusal", [made], results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
