"""What palette accuracy costs in time: the hull method against the refined one.

Single scikit-image photos and stitched sets (the demo's four photos, six photos
stitched, and the six with a synthetic colour wheel), K = 4..10, both palette
methods in the same run: palette time (best of two), MVC weights time (per
distinct colour, then scattered to every pixel), reconstruction RMSE (0-255, per
channel) over all pixels and of the worst image, the mean number of weights above
1/255 per pixel, and the farthest palette colour's distance (0-255) to a common
colour (a 5-bit bin covering at least 0.05 % of the pixels). Prints the table and
the issue's targets, saves rows as JSON and an accuracy-versus-time plot.

    python benchmarks/bench_decompose.py [--out benchmarks/out] [--cases NAME ...]

Reference (Tan, Echevarria, Gingold 2018, published RGBXY code on a 2-core
machine): palette 4-13 s, weights 3-7 s; RMSE at K = 6 astronaut 1.43,
chelsea 0.48, rocket 2.34, hubble_deep_field 1.64; coffee 0.45 at K = 8.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import skimage.color
import skimage.data

from palette_core import ColourSet, LoadedImage, find_images, rgb_to_mvc_weights
from palette_core.io import load_images
from palette_core.palettes import palette_polytope
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/out", help="folder for the plot and JSON")
    parser.add_argument("--cases", nargs="+", default=None, help="photo or set names")
    args = parser.parse_args()

    warm = ColourSet.from_images([photo("chelsea")])  # compile the kernels before timing
    for method in METHODS:
        palette_polytope(warm.colours, warm.counts, 5, None, method)

    rows = []
    header = (f"{'case':<18} {'Mpx':>5} {'K':>3} {'method':>8} {'palette s':>9} "
              f"{'weights s':>9} {'RMSE':>7} {'worst':>7} {'ref':>5} {'w>1/255':>7} "
              f"{'farthest':>8}")
    print(header)
    print("-" * len(header))
    for name, images in cases(args.cases).items():
        colour_set = ColourSet.from_images(images)
        mpx = colour_set.offsets[-1] / 1e6
        for k in range(4, 11):
            for method in METHODS:
                row = measure(colour_set, k, method) | {"case": name, "mpx": mpx, "k": k,
                                                        "method": method}
                rows.append(row)
                ref = REFERENCE_RMSE.get((name, k), "")
                print(f"{name:<18} {mpx:>5.2f} {row['K']:>3} {method:>8} "
                      f"{row['palette_s']:>9.3f} {row['weights_s']:>9.3f} {row['rmse']:>7.3f} "
                      f"{row['worst']:>7.3f} {ref:>5} {row['active']:>7.2f} "
                      f"{row['farthest']:>8.1f}", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "decompose.json").write_text(json.dumps(rows, indent=1))
    targets(rows)
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
    print(f"saved {out / 'accuracy_vs_time.png'} and {out / 'decompose.json'}")


if __name__ == "__main__":
    main()
