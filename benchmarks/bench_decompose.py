"""What palette accuracy costs in time: the hull method against the refined one.

Single scikit-image photos and stitched sets (the demo's four photos, six photos
stitched, and the six with a synthetic colour wheel), K = 4..10, both palette
methods in the same run: palette time (best of two), MVC weights time (per
distinct colour, then scattered to every pixel), reconstruction RMSE (0-255, per
channel) over all pixels and of the worst image, the mean number of weights above
1/255 per pixel, and the farthest palette colour's distance (0-255) to a common
colour (a 5-bit bin covering at least 0.05 % of the pixels). Prints the table and
the targets; writes ``benchmarks/results/decompose.json`` and an accuracy-versus-time plot.

    python benchmarks/bench_decompose.py [--out benchmarks/out] [--cases NAME ...]
    python benchmarks/bench_decompose.py --profile [--reference CHECKOUT PYTHON]

Reference (Tan, Echevarria, Gingold 2018, published RGBXY code on a 2-core
machine): palette 4-13 s, weights 3-7 s; RMSE at K = 6 astronaut 1.43,
chelsea 0.48, rocket 2.34, hubble_deep_field 1.64; coffee 0.45 at K = 8.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import skimage.color
import skimage.data
from PIL import Image
from results import table, write_result

from palette_core import ColourSet, LoadedImage, find_images, rgb_to_mvc_weights
from palette_core.io import load_images
from palette_core.palettes import palette_polytope
from palette_core.polytope import polytope_rmse
from palette_core.refine import binned_colours, common_colours

PHOTOS = ["astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "retina"]
METHODS = ["hull", "refined"]
REFERENCE_RMSE = {("astronaut", 6): 1.43, ("chelsea", 6): 0.48, ("rocket", 6): 2.34,
                  ("hubble_deep_field", 6): 1.64, ("coffee", 8): 0.45}
DEMO = Path(__file__).resolve().parent.parent / "examples" / "photos"


def photo(name: str) -> LoadedImage:
    pixels = getattr(skimage.data, name)()
    if pixels.ndim == 2:
        pixels = np.repeat(pixels[..., None], 3, axis=-1)
    return LoadedImage(name, np.ascontiguousarray(pixels[..., :3]), np.ones(pixels.shape[:2], bool))


def colour_wheel(size: int = 512) -> LoadedImage:
    """Every hue around, saturation growing outwards, full value: a hull near the cube's."""
    yy, xx = (np.mgrid[0:size, 0:size] + 0.5) / size * 2 - 1
    hsv = np.stack([(np.arctan2(yy, xx) / (2 * np.pi)) % 1, np.clip(np.hypot(xx, yy), 0, 1),
                    np.ones_like(xx)], axis=-1)
    pixels = np.round(skimage.color.hsv2rgb(hsv) * 255).astype(np.uint8)
    return LoadedImage("colour_wheel", pixels, np.ones(pixels.shape[:2], bool))


def cases(selected: list[str] | None) -> dict[str, list[LoadedImage]]:
    root, paths = find_images([DEMO])
    found = {name: [photo(name)] for name in PHOTOS}
    found["demo set"] = load_images(paths, root)
    found["six stitched"] = [photo(name) for name in PHOTOS]
    found["six + wheel"] = found["six stitched"] + [colour_wheel()]
    return {name: images for name, images in found.items() if not selected or name in selected}


def farthest_from_common(poly, colour_set: ColourSet) -> float:
    used = colour_set.counts > 0
    common = common_colours(*binned_colours(colour_set.colours[used], colour_set.counts[used]))
    distance = np.sqrt(((poly.vertices[:, None] - common[None]) ** 2).sum(-1)).min(axis=1)
    return 255.0 * float(distance.max())


def measure(colour_set: ColourSet, k: int, method: str) -> dict:
    times = []
    for _ in range(2):
        start = time.perf_counter()
        poly = palette_polytope(colour_set.colours, colour_set.counts, k, None, method)
        times.append(time.perf_counter() - start)
    start = time.perf_counter()
    weights = rgb_to_mvc_weights(colour_set.colours, poly)[colour_set.inverse]
    weights_s = time.perf_counter() - start
    squared = np.sum((weights @ poly.vertices - colour_set.colours[colour_set.inverse]) ** 2, 1)
    per_image = [255.0 * np.sqrt(squared[a:b].mean() / 3)
                 for a, b in zip(colour_set.offsets[:-1], colour_set.offsets[1:])]
    return {
        "K": len(poly.vertices), "palette_s": min(times), "weights_s": weights_s,
        "rmse": 255.0 * float(np.sqrt(squared.mean() / 3)), "worst": float(max(per_image)),
        "active": float(np.mean(np.sum(weights > 1 / 255, axis=1))),
        "farthest": farthest_from_common(poly, colour_set),
    }


PROFILED = [("astronaut", 6), ("coffee", 6), ("coffee", 8), ("chelsea", 6), ("rocket", 6),
            ("hubble_deep_field", 6)]


#: Times the first call of a numba kernel (a projection) in a fresh process: numba then
#: loads its typing and lowering registries, whichever kernel comes first.
FIRST_KERNEL_CALL = """
import time
import numpy as np
from palette_core.polytope import polytope_from_points, project_to_polytope
poly = polytope_from_points(np.eye(3).tolist() + [[0, 0, 0]])
start = time.perf_counter()
project_to_polytope(np.ones((1, 3)), poly)
print(time.perf_counter() - start)
"""


def profile(photos: list[tuple[str, int]], reference: list[str] | None = None) -> None:
    """The refined palette step by stage, in this process (kernels compiled): the hull
    simplification (its collapse LPs apart) and the refined palette, each the best of 3,
    the refinement being their difference; then one fresh ``palette-decompose`` process
    per photo (best of 3 wall times), split by the stage times it prints, the rest being
    Python's start and the imports; with ``reference`` (a checkout and its Python), the
    reference's palette step in a fresh process (``reference_hull.py``, once) and its time
    over ours, in a fresh process and warm. Last, numba's first kernel call in a fresh
    process (``FIRST_KERNEL_CALL``, best of 3), a part of the palette stage above that no
    palette work can remove. Run it with ``PYTHONPATH=<another checkout>`` to profile that
    code the same way."""
    import subprocess
    import sys
    import tempfile

    from palette_core import hull

    solve = hull._solve_collapses
    spent = [0.0]

    def timed(*args):
        start = time.perf_counter()
        try:
            return solve(*args)
        finally:
            spent[0] += time.perf_counter() - start

    hull._solve_collapses = timed
    print(f"{'photo':<18} {'K':>2} {'hull s':>7} {'of it LPs':>9} {'refine s':>8} {'RMSE':>6} "
          f"| {'process s':>9} {'start+imports':>13} {'load':>5} {'palette':>7} {'weights':>7}"
          + (f" | {'reference s':>11} {'x fresh':>7} {'x warm':>6}" if reference else ""))
    with tempfile.TemporaryDirectory() as folder:
        for name, k in photos:
            colour_set = ColourSet.from_images([photo(name)])
            colours, counts = colour_set.colours, colour_set.counts
            palette_polytope(colours, counts, k)  # compile
            hulls, palettes = [], []  # each the best of 3 alone: the refinement is the rest
            for _ in range(3):
                spent[0] = 0.0
                start = time.perf_counter()
                hull.extract_palette(colours, counts, k)
                hulls.append((time.perf_counter() - start, spent[0]))
                start = time.perf_counter()
                poly = palette_polytope(colours, counts, k)
                palettes.append(time.perf_counter() - start)
            (hull_s, lp_s), palette_s = min(hulls), min(palettes)
            best = {"hull": hull_s, "lp": lp_s, "refine": palette_s - hull_s}
            rmse = polytope_rmse(colours, counts, poly)
            png = Path(folder) / f"{name}.png"
            Image.fromarray(photo(name).pixels).save(png)
            runs = []
            for _ in range(3):
                start = time.perf_counter()
                done = subprocess.run([sys.executable, "-m", "palette_core.cli.decompose",
                                       str(png), "-k", str(k), "-o", str(Path(folder) / "w.npz"),
                                       "--force"], capture_output=True, text=True, check=True,
                                      cwd=folder)  # not this checkout's palette_core
                runs.append((time.perf_counter() - start, done.stdout))
            wall, stdout = min(runs)
            stages = dict(part.split()[:2] for part in
                          stdout.split("time: ")[1].splitlines()[0].split(", "))
            stages = {key: float(value) for key, value in stages.items()}
            print(f"{name:<18} {k:>2} {best['hull']:>7.3f} {best['lp']:>9.3f} "
                  f"{best['refine']:>8.3f} {rmse:>6.3f} | {wall:>9.2f} "
                  f"{wall - sum(stages.values()):>13.2f} {stages['load']:>5.2f} "
                  f"{stages['palette']:>7.2f} {stages['weights']:>7.2f}"
                  + (_versus_reference(reference, png, k, folder, stages["palette"],
                                       best["hull"] + best["refine"]) if reference else ""),
                  flush=True)
    first = min(float(subprocess.run([sys.executable, "-c", FIRST_KERNEL_CALL], capture_output=True,
                                     text=True, check=True).stdout) for _ in range(3))
    print(f"numba's first kernel call in a fresh process: {first:.2f} s (best of 3)")


def _versus_reference(reference: list[str], png: Path, k: int, folder: str, fresh: float,
                      warm: float) -> str:
    """The reference's palette time for ``png`` and how many times ours it is."""
    import subprocess

    checkout, python = reference
    done = subprocess.run([python, str(Path(__file__).parent / "reference_hull.py"), checkout,
                           str(png), str(k), str(Path(folder) / "hull.obj")],
                          capture_output=True, text=True, check=True, cwd=folder)
    seconds = float(done.stdout.split("palette ")[1].split()[0])
    return f" | {seconds:>11.2f} {seconds / fresh:>7.0f} {seconds / warm:>6.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/out", help="folder for the plot")
    parser.add_argument("--cases", nargs="+", default=None, help="photo or set names")
    parser.add_argument("--profile", action="store_true",
                        help="only the palette step's stages and a fresh palette-decompose "
                             "process per photo (profile())")
    parser.add_argument("--reference", nargs=2, metavar=("CHECKOUT", "PYTHON"),
                        help="with --profile: time the reference hull simplification too "
                             "(benchmarks/reference_hull.py) from a clone of "
                             "CraGL/fastLayerDecomposition, run by PYTHON")
    args = parser.parse_args()
    if args.profile:
        profile(PROFILED, args.reference)
        return

    warm = ColourSet.from_images([photo("chelsea")])  # compile the kernels before timing
    for method in METHODS:
        palette_polytope(warm.colours, warm.counts, 5, None, method)

    rows = []
    for name, images in cases(args.cases).items():
        colour_set = ColourSet.from_images(images)
        mpx = colour_set.offsets[-1] / 1e6
        for k in range(4, 11):
            for method in METHODS:
                row = measure(colour_set, k, method) | {"case": name, "mpx": mpx, "k": k,
                                                        "method": method}
                rows.append(row)
                print(f"{name} K={k} {method}: RMSE {row['rmse']:.3f}, palette "
                      f"{row['palette_s']:.3f} s", flush=True)
    made = table("Palette methods, K = 4..10", [
        "case", "Mpx", "K", "method", "palette s", "weights s", "RMSE", "worst image",
        "reference RMSE", "weights > 1/255", "farthest colour"], [
        [r["case"], round(r["mpx"], 2), r["K"], r["method"], round(r["palette_s"], 3),
         round(r["weights_s"], 3), round(r["rmse"], 3), round(r["worst"], 3),
         REFERENCE_RMSE.get((r["case"], r["k"]), ""), round(r["active"], 2),
         round(r["farthest"], 1)] for r in rows])
    write_result("decompose", "Palettes: what accuracy costs in time", [made], {"rows": rows})
    targets(rows)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plot(rows, out)


def targets(rows: list[dict]) -> None:
    """The palette-fidelity targets, measured on these rows."""
    def row(case, k, method):
        return next((r for r in rows if (r["case"], r["k"], r["method"]) == (case, k, method)),
                    None)

    print("\nTargets")
    demo, demo_hull = row("demo set", 6, "refined"), row("demo set", 6, "hull")
    if demo:
        print(f"  demo set, K = 6: RMSE {demo['rmse']:.3f} (target <= 1.0), worst photo "
              f"{demo['worst']:.3f} (target <= 1.5); hull method "
              f"{demo_hull['rmse']:.3f} / {demo_hull['worst']:.3f}")
    six = row("six stitched", 6, "refined")
    if six:
        before = row("six stitched", 6, "hull")
        print(f"  six stitched, K = 6: RMSE {before['rmse']:.3f} -> {six['rmse']:.3f}, "
              f"{before['rmse'] / six['rmse']:.1f}x lower (target >= 5x); palette "
              f"{six['palette_s']:.2f} s for {six['mpx']:.2f} Mpx (target <= 1.5 s for 1.5 Mpx)")
    singles = [(r, row(r["case"], r["k"], "hull")) for r in rows
               if r["method"] == "refined" and r["case"] in PHOTOS]
    if singles:
        worse = [f"{r['case']} K={r['k']}" for r, h in singles if r["rmse"] > 1.02 * h["rmse"]]
        ratios = [r["palette_s"] / h["palette_s"] for r, h in singles]
        print(f"  single photos worse than the hull method by > 2 %: {worse or 'none'}")
        print(f"  single photos, palette time refined / hull: median {np.median(ratios):.2f}x, "
              f"max {max(ratios):.2f}x (target <= 1.2x)")
    far = [r["farthest"] for r in rows if r["method"] == "refined"]
    if far:
        within = sum(f <= 60.5 for f in far)
        print(f"  palettes with every colour within 60 of a common colour: {within} of {len(far)} "
              f"(hull method: {sum(r['farthest'] <= 60.5 for r in rows if r['method'] == 'hull')})")


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for i, name in enumerate(dict.fromkeys(r["case"] for r in rows)):
        for method, style in zip(METHODS, ("o--", "s-")):
            mine = [r for r in rows if r["case"] == name and r["method"] == method]
            ax.plot([r["palette_s"] + r["weights_s"] for r in mine], [r["rmse"] for r in mine],
                    style, color=f"C{i}", label=f"{name} ({method})", alpha=0.9,
                    markersize=4)
    ax.set_xlabel("palette + MVC weights time (s)")
    ax.set_ylabel("reconstruction RMSE (0-255)")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.set_title("Accuracy against time, K = 4..10: hull (dashed) and refined (solid)")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "accuracy_vs_time.png", dpi=120)
    print(f"saved {out / 'accuracy_vs_time.png'}")


if __name__ == "__main__":
    main()
