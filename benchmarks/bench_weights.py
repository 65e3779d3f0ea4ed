"""MVC against RGBXY weights on the scikit-image sample photos, at K = 5, 6, 8.

For each photo and K, with the same palette for both methods: reconstruction
RMSE (0-255, per channel), sparsity (mean count of weights above 1/255 per
pixel, and the share of pixels using at most 3 colours), spatial smoothness
(mean gradient magnitude of the weight maps, per map and pixel), time of the
weights, and peak memory (the rise of the process's peak resident set, Linux
``VmHWM``, Qhull's own memory included). Prints a table and saves a figure of
both methods' weight maps for one photo.

    python benchmarks/bench_weights.py [--out benchmarks/out] [--photos ...] [--ks 5 6 8]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import skimage.data
from results import table, write_result

from palette_core import WEIGHT_METHODS, ColourSet, LoadedImage, extract_palette, image_weights

PHOTOS = ["astronaut", "coffee", "chelsea", "rocket"]


def _memory_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def measure(
    method: str, colour_set: ColourSet, image: LoadedImage, poly
) -> tuple[dict, np.ndarray]:
    Path("/proc/self/clear_refs").write_text("5")  # reset the peak resident set
    before = _memory_kib("VmRSS")
    start = time.perf_counter()
    (weights,) = image_weights(colour_set, poly, method)
    seconds = time.perf_counter() - start
    peak_mib = (_memory_kib("VmHWM") - before) / 1024
    flat = weights.reshape(-1, weights.shape[-1]).astype(np.float64)
    error = flat @ poly.vertices - image.rgb.reshape(-1, 3)
    active = np.sum(flat > 1 / 255, axis=1)
    gy, gx = np.gradient(weights.astype(np.float64), axis=(0, 1))
    return {
        "rmse": 255.0 * float(np.sqrt(np.mean(error**2))),
        "active": float(active.mean()),
        "at_most_3": float(np.mean(active <= 3)),
        "gradient": float(np.mean(np.hypot(gx, gy))),
        "seconds": seconds,
        "peak_mib": peak_mib,
    }, weights


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/out", help="folder for the figure")
    parser.add_argument("--photos", nargs="+", default=PHOTOS)
    parser.add_argument("--ks", nargs="+", type=int, default=[5, 6, 8])
    parser.add_argument("--figure-photo", default="chelsea")
    args = parser.parse_args()

    warm = LoadedImage("warm", np.random.default_rng(0).integers(0, 256, (8, 8, 3), np.uint8),
                       np.ones((8, 8), bool))
    warm_set = ColourSet.from_images([warm])
    for method in WEIGHT_METHODS:  # compile the numba kernels before timing
        measure(method, warm_set, warm, extract_palette(warm_set.colours, warm_set.counts, 4))

    figure, rows, results = {}, [], []
    for name in args.photos:
        pixels = getattr(skimage.data, name)()[..., :3]
        image = LoadedImage(name, pixels, np.ones(pixels.shape[:2], bool))
        colour_set = ColourSet.from_images([image])
        for k in args.ks:
            poly = extract_palette(colour_set.colours, colour_set.counts, k)
            for method in WEIGHT_METHODS:
                row, weights = measure(method, colour_set, image, poly)
                megapixels = pixels.shape[0] * pixels.shape[1] / 1e6
                print(f"{name} K={len(poly.vertices)} {method}: {row}", flush=True)
                results.append({"photo": name, "megapixels": megapixels,
                                "k": len(poly.vertices), "method": method, **row})
                rows.append([name, round(megapixels, 2), len(poly.vertices), method,
                             round(row["rmse"], 3), round(row["active"], 2),
                             f"{row['at_most_3']:.1%}", round(row["gradient"], 4),
                             round(row["seconds"], 2), round(row["peak_mib"])])
                if name == args.figure_photo and k == 6:
                    figure[method] = (weights, poly.vertices)
    made = table("MVC against RGBXY", ["photo", "Mpx", "K", "method", "RMSE (0-255)",
                                       "weights > 1/255", "<= 3 colours", "gradient",
                                       "seconds", "peak MiB"], rows)
    write_result("weights", "Weights: MVC against RGBXY", [made], {"rows": results})
    if figure:
        save_figure(figure, args.figure_photo, Path(args.out))


def save_figure(figure: dict, photo: str, out: Path) -> None:
    """One row per method: each weight map, titled by its palette colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k = len(next(iter(figure.values()))[1])
    fig, axes = plt.subplots(len(figure), k + 1, figsize=(2.2 * (k + 1), 2.2 * len(figure)))
    for row, (method, (weights, palette)) in enumerate(figure.items()):
        axes[row, 0].imshow(np.clip(weights.astype(np.float64) @ palette, 0, 1))
        axes[row, 0].set_title(f"{method}: recon.", fontsize=9)
        for j in range(k):
            axes[row, j + 1].imshow(weights[..., j], cmap="gray", vmin=0, vmax=1)
            axes[row, j + 1].set_title(f"{method} w{j}", fontsize=9,
                                       color=np.clip(palette[j], 0, 0.85))
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle(f"{photo}: weight maps, MVC (top) and RGBXY (bottom), K = {k}")
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "weights_mvc_vs_rgbxy.png"
    fig.savefig(path, dpi=110)
    print(f"saved {path}")


if __name__ == "__main__":
    main()
