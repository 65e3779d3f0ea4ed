"""What palette accuracy costs in time, on the scikit-image sample photos.

For K = 4..10 and for --max-error tolerances: palette time, MVC weights time
(per distinct colour, then scattered to every pixel), reconstruction RMSE
(0-255, per channel) and the mean number of weights above 1/255 per pixel.
Prints a table and saves an accuracy-versus-time plot.

    python benchmarks/bench_decompose.py [--out benchmarks/out]

Reference (Tan, Echevarria, Gingold 2018, published RGBXY code on a 2-core
machine): palette 4-13 s, weights 3-7 s; RMSE at K = 6 astronaut 1.43,
chelsea 0.48, rocket 2.34, hubble_deep_field 1.64; coffee 0.45 at K = 8.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import skimage.data

from palette_core import ColourSet, LoadedImage, extract_palette, rgb_to_mvc_weights

PHOTOS = ["astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "retina"]
REFERENCE_RMSE = {("astronaut", 6): 1.43, ("chelsea", 6): 0.48, ("rocket", 6): 2.34,
                  ("hubble_deep_field", 6): 1.64, ("coffee", 8): 0.45}


def measure(colour_set: ColourSet, image: LoadedImage, k, max_error) -> dict:
    start = time.perf_counter()
    poly = extract_palette(colour_set.colours, colour_set.counts, k, max_error)
    palette_s = time.perf_counter() - start
    start = time.perf_counter()
    weights = rgb_to_mvc_weights(colour_set.colours, poly)[colour_set.inverse]
    weights_s = time.perf_counter() - start
    error = weights @ poly.vertices - image.rgb.reshape(-1, 3)
    return {
        "K": len(poly.vertices),
        "palette_s": palette_s,
        "weights_s": weights_s,
        "rmse": 255.0 * float(np.sqrt(np.mean(error**2))),
        "active": float(np.mean(np.sum(weights > 1 / 255, axis=1))),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/out", help="folder for the plot")
    parser.add_argument("--photos", nargs="+", default=PHOTOS)
    parser.add_argument("--tolerances", nargs="+", type=float, default=[4.0, 2.0, 1.0, 0.5])
    args = parser.parse_args()

    warm = np.random.default_rng(0).random((100, 3))  # compile the kernels before timing
    rgb_to_mvc_weights(warm, extract_palette(warm, np.ones(100, int), k=5))

    rows = []
    header = (f"{'photo':<18} {'Mpx':>5} {'setting':>9} {'K':>3} {'palette s':>9} "
              f"{'weights s':>9} {'RMSE':>7} {'ref':>5} {'w>1/255':>7}")
    print(header)
    print("-" * len(header))
    for name in args.photos:
        pixels = getattr(skimage.data, name)()[..., :3]
        image = LoadedImage(name, pixels, np.ones(pixels.shape[:2], bool))
        colour_set = ColourSet.from_images([image])
        settings = [(k, None, f"k={k}") for k in range(4, 11)]
        settings += [(None, e, f"E={e:g}") for e in args.tolerances]
        for k, max_error, label in settings:
            row = measure(colour_set, image, k, max_error)
            row.update(photo=name, setting=label, mpx=pixels.shape[0] * pixels.shape[1] / 1e6)
            rows.append(row)
            ref = REFERENCE_RMSE.get((name, k))
            print(f"{name:<18} {row['mpx']:>5.2f} {label:>9} {row['K']:>3} "
                  f"{row['palette_s']:>9.3f} {row['weights_s']:>9.3f} {row['rmse']:>7.3f} "
                  f"{ref if ref else '':>5} {row['active']:>7.2f}")
    plot(rows, Path(args.out))


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name in dict.fromkeys(r["photo"] for r in rows):
        mine = [r for r in rows if r["photo"] == name and r["setting"].startswith("k=")]
        ax.plot([r["palette_s"] + r["weights_s"] for r in mine], [r["rmse"] for r in mine],
                "o-", label=name)
        for r in mine:
            ax.annotate(str(r["K"]), (r["palette_s"] + r["weights_s"], r["rmse"]), fontsize=7)
    ax.set_xlabel("palette + MVC weights time (s)")
    ax.set_ylabel("reconstruction RMSE (0-255)")
    ax.set_yscale("symlog", linthresh=0.1)
    ax.set_title("Accuracy against time, K = 4..10 (labels: K)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "accuracy_vs_time.png", dpi=120)
    print(f"saved {out / 'accuracy_vs_time.png'}")


if __name__ == "__main__":
    main()
