"""Splat files of other tools palette-edited (docs/splat_files.md): the time and peak memory
to read, decompose and write them, how well the palette explains them and how far a local
edit leaks, on public splat files and on synthetic scenes of 1 and 3 million splats.

Public files (fetch them with the search tool's ``fetch``; none is committed), in ROOT:

- ``biker.compressed.ply``, ``biker.spz``, ``guitar.compressed.ply``:
  ``playcanvas/engine`` ``examples/assets/splats/``;
- ``playbot/``: the SOG of ``playcanvas/engine`` ``examples/assets/splats/playbot/3_0/``
  (CC-BY-4.0, Stephane Agullo);
- any other ``.ply``, ``.spz``, ``.splat`` or ``.sog`` put there (a splat run of ours
  exported with ``nerf-stage export RUN -o ROOT/run.ply``).

Each file goes through the commands in a child process of its own: ``palette-decompose
FILE -k 6`` (read, palette, weights, the splat stack written), then ``palette-recolor`` of
an edit (palette colour 0 turned red) into a PLY; the child's peak resident memory is its
``VmHWM``. Synthetic scenes (random splats of degree 3 in a cube) are written first as
PLYs of ``--millions`` million splats.

For the public files, ``--views`` views around the scene (an orbit about the splats'
vertical axis, at 256 x 256, drawn by ``nerf_stage.splats.draw``) score:

- *identity*: the unedited palette's file against the original: the largest difference of
  any pixel (0: equal);
- *palette*: the splats with their colours replaced by ``weights @ palette`` (the degree-0
  colour alone; view dependence kept) against the original: how much of the scene the
  six colours explain;
- *leakage*: the edit's mean change (0-255) over the pixels the selection does not reach
  (where the selected splats' composited coverage is under 1 %), and its mean change where
  it does;
- *studio*: the splat stack opened in the studio, and a palette edit's new colours for the
  page, the server's part (``studio_edit``).

With ``--runs RUN ...`` (splat runs of ours, additive basis), the ``--residual`` modes: its
splats' residual lives in weight space, so its own export with an edited palette is how
its view-dependent colour should follow the edit; its export with its own palette, given
its weights as a splat stack, is recoloured by each mode and scored against that.

    python benchmarks/bench_splat_files.py ROOT [--out DIR] [--millions 1 3] [--views 8]
        [--runs RUN ...]
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from results import table, write_result

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from palette_core.palette_file import write_palette_json  # noqa: E402
from splat_files import SplatFields, is_splat_file, read_splat_file, write_splat_file  # noqa: E402
from splat_files.fields import SH_C0  # noqa: E402
from splat_files.stack import RESIDUALS, read_splat_stack  # noqa: E402

SIZE = 256


def child(code: str) -> tuple[float, float, str]:
    """Seconds, peak resident MB (``VmHWM``) and stdout of ``python -c code``."""
    with tempfile.NamedTemporaryFile("r") as peak:
        wrapped = (f"import sys\ntry:\n    {code}\nfinally:\n    open({peak.name!r}, 'w').write("
                   "[l for l in open('/proc/self/status') if l.startswith('VmHWM')][0])")
        start = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", wrapped], capture_output=True, text=True,
                              cwd=ROOT)
        seconds = time.perf_counter() - start
        if done.returncode:
            sys.exit(f"failed: {code}\n{done.stderr[-2000:]}")
        return seconds, int(Path(peak.name).read_text().split()[1]) / 1024, done.stdout


def command(module: str, argv: list[str]) -> str:
    return f"from {module} import main; sys.exit(main({[str(a) for a in argv]!r}))"


def synthetic(path: Path, millions: float, rng) -> Path:
    """A PLY of ``millions`` million random splats of degree 3 in a cube."""
    if path.is_file():
        return path
    n = round(millions * 1e6)
    fields = SplatFields(rng.uniform(-1, 1, (n, 3)).astype(np.float32),
                         rng.normal(0, 1, (n, 3)).astype(np.float32),
                         rng.normal(0, 0.1, (n, 15, 3)).astype(np.float32),
                         rng.normal(0, 2, n).astype(np.float32),
                         rng.uniform(-6, -3, (n, 3)).astype(np.float32),
                         rng.normal(size=(n, 4)).astype(np.float32))
    return write_splat_file(fields, path)


def pipeline(path: Path, out: Path) -> dict:
    """``palette-decompose`` and ``palette-recolor`` of one file, each in a child."""
    stack = out / f"{path.name.split('.')[0]}.splats.npz"
    decompose = command("palette_core.cli.decompose",
                        [path, "-k", 6, "-o", stack, "--force"])
    seconds, peak, printed = child(decompose)
    timings = dict(part.split(" ")[:2] for part in
                   next(line for line in printed.splitlines() if line.startswith("time:"))
                   [6:].split(", "))
    edited = read_splat_stack(stack).palette.copy()
    edited[0] = [1.0, 0.1, 0.1]
    palette = out / "edit.json"
    with open(palette, "w") as file:
        write_palette_json(file, edited)
    recoloured = out / f"{path.name.split('.')[0]}.edited.ply"
    recolor = command("palette_core.cli.recolor", [stack, "--palette", palette,
                                                   "--select-colour", 0, "-o", recoloured,
                                                   "--force"])
    recolor_seconds, recolor_peak, _ = child(recolor)
    return {"stack": stack, "edited": recoloured, "decompose_s": seconds,
            "decompose_mb": peak, "recolor_s": recolor_seconds, "recolor_mb": recolor_peak,
            **{f"{k}_s": float(v) for k, v in timings.items()}}


def orbit(fields: SplatFields, views: int) -> tuple[np.ndarray, float]:
    """(V, 4, 4) poses around the splats' middle, about their vertical axis (the PLY's -y),
    20 degrees above it, far enough to see their central 90 %; the vertical field of view."""
    from nerf_stage.data.cameras import look_at

    low, high = np.percentile(fields.means, [5, 95], axis=0)
    centre, reach = (low + high) / 2, float(np.linalg.norm(high - low)) / 2
    fov = math.radians(50)
    distance = 1.2 * reach / math.sin(fov / 2)
    poses = []
    for angle in np.linspace(0, 2 * math.pi, views, endpoint=False):
        offset = np.array([math.sin(angle), -math.tan(math.radians(20)), math.cos(angle)])
        poses.append(look_at(centre + distance * offset / np.linalg.norm(offset), centre,
                             up=(0.0, -1.0, 0.0)))
    return np.stack(poses), fov


def rendered(fields: SplatFields, poses: np.ndarray, fov: float,
             values: np.ndarray | None = None) -> np.ndarray:
    """(V, H, W, C) the splats drawn from ``poses``: their view-dependent colours (3D
    Gaussian splatting's, clipped to [0, 1]) on black, or other (S, C) ``values``."""
    import torch

    from nerf_stage.data.cameras import Intrinsics
    from nerf_stage.splats import draw
    from nerf_stage.splats.model import covariances
    from nerf_stage.splats.sh import sh_basis

    focal = 0.5 * SIZE / math.tan(fov / 2)
    camera = Intrinsics(SIZE, SIZE, focal, focal, SIZE / 2, SIZE / 2)
    centres = torch.as_tensor(fields.means)
    cov = covariances(torch.as_tensor(fields.quats, dtype=torch.float64),
                      torch.as_tensor(np.exp(fields.scales.astype(np.float64)))).float()
    opacity = torch.sigmoid(torch.as_tensor(fields.opacities))
    images = []
    for pose in poses:
        if values is None:
            direction = torch.nn.functional.normalize(centres - torch.as_tensor(
                pose[:3, 3], dtype=torch.float32), dim=1)
            colour = SH_C0 * torch.as_tensor(fields.sh0) + 0.5 + torch.einsum(
                "sb,sbc->sc", sh_basis(direction, fields.degree)[:, 1:],
                torch.as_tensor(fields.shN))
            shown = colour.clamp(0, 1)
        else:
            shown = torch.as_tensor(values, dtype=torch.float32)
        with torch.no_grad():
            drawn, _ = draw(centres, cov, shown, opacity, torch.as_tensor(pose), camera, None)
        images.append(drawn.view(SIZE, SIZE, -1).numpy())
    return np.stack(images)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(1 / mse)


def fidelity(path: Path, done: dict, views: int, out: Path) -> dict:
    """The identity's and the palette's PSNR and the edit's leakage over ``views`` views,
    and a picture: original | edited | change, for two views."""
    original = read_splat_file(path)
    stack = read_splat_stack(done["stack"])
    poses, fov = orbit(original, views)
    truth = rendered(original, poses, fov)
    same = rendered(stack.recoloured(stack.palette), poses, fov)
    base = np.clip(stack.weights.astype(np.float64) @ stack.palette, 0, 1)
    palette_only = original.with_colour((base - 0.5) / SH_C0, original.shN)
    explained = rendered(palette_only, poses, fov)
    edited = rendered(read_splat_file(done["edited"]), poses, fov)
    selected = (stack.weights[:, 0] >= 0.5).astype(np.float32)[:, None]
    reach = rendered(original, poses, fov, selected)[..., 0]
    change = 255 * np.abs(edited - truth).mean(-1)
    outside = reach < 0.01
    picture = np.concatenate([np.concatenate([truth[i], edited[i], np.repeat(
        np.clip(change[i] / 64, 0, 1)[..., None], 3, -1)], 1) for i in range(2)], 0)
    from PIL import Image

    Image.fromarray((picture * 255).round().astype(np.uint8)).save(
        out / f"{path.name.split('.')[0]}-edit.png")
    return {"identity_difference": float(np.abs(same - truth).max()),
            "palette_psnr": psnr(explained, truth),
            "leak_outside": float(change[outside].mean()) if outside.any() else 0.0,
            "change_inside": float(change[~outside].mean()) if (~outside).any() else 0.0,
            "outside_share": float(outside.mean())}


def studio_edit(path: Path, repeats: int = 5) -> dict:
    """Seconds to open ``path``'s splat stack in the studio (``SplatFileTarget``: the splats
    the browser draws) and the server's part of a palette edit, median of ``repeats``: the
    splats' new colours (``SceneView.splat_colours``) as the bytes the page gets."""
    from studio.app import Studio
    from studio.splat_file import SplatFileTarget

    start = time.perf_counter()
    target = SplatFileTarget.open(path)
    opened = time.perf_counter() - start
    studio = Studio(target, port=0)
    try:
        times = []
        for i in range(repeats):
            colour = np.array([i / repeats, 0.2, 0.3])
            start = time.perf_counter()
            studio._apply(lambda colour=colour: studio.editor.set_colour(0, colour))
            np.ascontiguousarray(np.round(studio.view.splat_colours() * 255), np.uint8)
            times.append(time.perf_counter() - start)
    finally:
        studio.stop()
    return {"studio_open_s": opened, "studio_edit_ms": 1000 * float(np.median(times))}


def residual_modes(run_dir: Path, views: int) -> dict:
    """The view-dependent colour under an edit, each of ``RESIDUALS`` (and ``none``: dropped)
    against the truth of a splat run of ours: its splats' residual lives in weight space, so
    its own export with the edited palette is how the view dependence follows the edit.
    The run's export with its own palette, given the run's weights as a splat stack, is
    recoloured with two edits; PSNR over ``views`` views of an orbit."""
    from nerf_stage.splats import splat_fields
    from nerf_stage.train.loading import load_run
    from palette_core.basis import Basis
    from splat_files.stack import SplatStack

    splats = load_run(run_dir).splats({})
    if splats.basis != Basis.ADDITIVE:
        sys.exit(f"{run_dir}: residual modes need a run of the additive basis")
    fields = splat_fields(splats)
    stack = SplatStack(fields, splats.palette, splats.weights, np.zeros((0, 3), np.int32))
    poses, fov = orbit(fields, views)
    one = splats.palette.copy()
    one[0] = 1 - one[0]
    scores = {}
    for name, edited in {"one colour inverted": one, "palette reversed":
                         splats.palette[::-1].copy()}.items():
        truth = rendered(splat_fields(splats, edited), poses, fov)
        recoloured = {mode: stack.recoloured(edited, residual=mode) for mode in RESIDUALS}
        recoloured["none"] = recoloured["keep"].with_colour(recoloured["keep"].sh0,
                                                            fields.shN[:, :0])
        scores[name] = {mode: psnr(rendered(f, poses, fov), truth)
                        for mode, f in recoloured.items()}
    return scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("root", type=Path, help="folder of public splat files")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out/splat_files"))
    parser.add_argument("--millions", type=float, nargs="*", default=[1.0, 3.0])
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--runs", type=Path, nargs="*", default=[],
                        help="splat runs of ours (additive basis): their view-dependent colour "
                             "under edits, each residual mode against the run's own export")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    files = sorted(p for p in args.root.iterdir() if is_splat_file(p) or (
        p.is_dir() and (p / "meta.json").is_file()))
    files += [synthetic(args.out / f"random-{m:g}M.ply", m, rng) for m in args.millions]
    results, rows, scores, studio_rows = {}, [], [], []
    for path in files:
        fields = read_splat_file(path)
        done = pipeline(path, args.out)
        result = {"splats": len(fields), "degree": fields.degree, **{
            k: v for k, v in done.items() if k not in ("stack", "edited")}}
        print(f"{path.name}: {len(fields)} splats, decompose {done['decompose_s']:.1f} s "
              f"({done['decompose_mb']:.0f} MB), recolour {done['recolor_s']:.1f} s", flush=True)
        rows.append([path.name, len(fields), fields.degree, round(done["read_s"], 2),
                     round(done["palette_s"], 2), round(done["weights_s"], 2),
                     round(done["decompose_s"], 1), round(done["decompose_mb"]),
                     round(done["recolor_s"], 1), round(done["recolor_mb"])])
        if not path.name.startswith("random-"):
            result.update(fidelity(path, done, args.views, args.out))
            scores.append([path.name, result["identity_difference"],
                           round(result["palette_psnr"], 2),
                           round(result["leak_outside"], 3), round(result["change_inside"], 2),
                           round(result["outside_share"], 3)])
        result.update(studio_edit(done["stack"]))
        studio_rows.append([path.name, len(fields), round(result["studio_open_s"], 1),
                            round(result["studio_edit_ms"], 1)])
        results[path.name] = result
    made = [table("Read, decompose and write, each command in a process of its own",
                  ["file", "splats", "degree", "read s", "palette s", "weights s",
                   "decompose s (whole command)", "peak MB", "recolour s (whole command)",
                   "peak MB"], rows),
            table(f"Rendered, {args.views} views at {SIZE} x {SIZE} around the scene",
                  ["file", "identity: largest difference", "palette PSNR", "leak outside (0-255)",
                   "change inside (0-255)", "share outside"], scores),
            table("The studio, its splat stack opened and a palette edit (the server's part, "
                  "median of 5)", ["file", "splats", "open s", "edit ms"], studio_rows)]
    modes = {run.name: residual_modes(run, args.views) for run in args.runs}
    if modes:
        results["residual modes"] = modes
        made.append(table("View-dependent colour under an edit: a splat run recoloured through "
                          "its splat file, against its own export (PSNR, dB)",
                          ["run", "edit", *RESIDUALS, "none"],
                          [[run, edit, *(round(row[m], 2) for m in (*RESIDUALS, "none"))]
                           for run, edits in modes.items() for edit, row in edits.items()]))
    write_result("splat_files", "Splat files of other tools, palette-edited", made, results)


if __name__ == "__main__":
    main()
