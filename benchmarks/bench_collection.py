"""Collections beyond memory: wall time per pass, peak memory, megapixels per second.

Generates, from the scikit-image photos (mosaics of crops with flips and noise, so
that colours stay realistic; never pure upscaling): 10 MP and 100 MP of 2 MP JPEGs,
and a 1-gigapixel video (500 frames of 1920x1080, a camera panning over such a
mosaic, H.264). Each is decomposed by `palette-decompose ... -o NAME.zarr` in one
process and with `--workers 2`, in a subprocess each (peak RSS of the command's
own process by /usr/bin/time: with `--workers 2` the workers' memory is not in
it); prints the table and saves `collection_growth.png` (time and memory against
size).

    python benchmarks/bench_collection.py [--out benchmarks/out] [--sizes 10 100 1000]
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import skimage.data
from PIL import Image
from results import table, write_result

from palette_core.outputs import atomic_outputs, publish_folder

PHOTOS = ["astronaut", "coffee", "chelsea", "rocket", "hubble_deep_field", "retina"]
TILE = 256


def photos() -> list[np.ndarray]:
    found = []
    for name in PHOTOS:
        pixels = getattr(skimage.data, name)()
        found.append(np.repeat(pixels[..., None], 3, -1) if pixels.ndim == 2 else pixels[..., :3])
    return found


def mosaic(rng, sources, height: int, width: int) -> np.ndarray:
    """Tiles of random crops of the photos, randomly flipped, with a little noise."""
    canvas = np.empty((height, width, 3), np.uint8)
    for top in range(0, height, TILE):
        for left in range(0, width, TILE):
            photo = sources[rng.integers(len(sources))]
            y = rng.integers(0, photo.shape[0] - TILE + 1)
            x = rng.integers(0, photo.shape[1] - TILE + 1)
            tile = photo[y:y + TILE, x:x + TILE]
            if rng.random() < 0.5:
                tile = tile[:, ::-1]
            if rng.random() < 0.5:
                tile = tile[::-1]
            h, w = min(TILE, height - top), min(TILE, width - left)
            canvas[top:top + h, left:left + w] = tile[:h, :w]
    noise = rng.normal(0, 2.0, canvas.shape)
    return np.clip(canvas + noise, 0, 255).astype(np.uint8)


def make_jpegs(folder: Path, n: int, rng) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    sources = photos()
    for i in range(n):
        Image.fromarray(mosaic(rng, sources, 1224, 1632)).save(folder / f"p{i:04d}.jpg",
                                                               quality=90)


def make_video(path: Path, frames: int, rng) -> None:
    """A camera panning over a large mosaic, 1920x1080 at 25 frames per second."""
    import av

    world = mosaic(rng, photos(), 1080 + 512, 1920 + 2 * frames)
    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264", rate=25, options={"preset": "ultrafast",
                                                                   "crf": "18"})
        stream.width, stream.height, stream.pix_fmt = 1920, 1080, "yuv420p"
        for i in range(frames):
            y = int(256 + 200 * np.sin(i / 40))
            view = np.ascontiguousarray(world[y:y + 1080, 2 * i:2 * i + 1920])
            container.mux(stream.encode(av.VideoFrame.from_ndarray(view, format="rgb24")))
        container.mux(stream.encode())


def run(inputs: list[str], data: Path, workers: int | None) -> dict:
    """Decompose ``inputs`` into a store in a fresh temporary folder in ``data`` (removed
    after measuring) and return the command's times, peak memory and store size."""
    data.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=data) as folder:
        store = Path(folder) / "store.zarr"
        command = ["/usr/bin/time", "-f", "maxrss %M", sys.executable, "-m",
                   "palette_core.cli.decompose", *inputs, "-k", "6", "-o", str(store)]
        if workers:
            command += ["--workers", str(workers)]
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(done.stderr[-2000:])
        size = sum(f.stat().st_size for f in store.rglob("*") if f.is_file())
    times = dict(re.findall(r"(\w+) ([\d.]+) s", done.stdout.split("time:")[1]))
    pixels = float(re.search(r"([\d.]+) Mpx", done.stdout).group(1))
    return {"mpx": pixels, "pass1_s": float(times["pass1"]), "palette_s": float(times["palette"]),
            "pass2_s": float(times["pass2"]),
            "rss_mb": int(re.search(r"maxrss (\d+)", done.stderr).group(1)) / 1024,
            "store_mb": size / 2**20, "workers": workers or 1}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/out")
    parser.add_argument("--data", default="benchmarks/out/collections",
                        help="where the generated collections go")
    parser.add_argument("--sizes", nargs="+", type=int, default=[10, 100, 1000],
                        help="megapixels: 10 and 100 as 2 MP JPEGs, 1000 as a video")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    data = Path(args.data)
    rows = []
    for size in args.sizes:
        if size >= 1000:
            source = data / "video.mp4"
            if not source.exists():  # written beside it, renamed when complete
                with atomic_outputs() as stage:
                    make_video(stage(source), size // 2, rng)
            label = f"{size // 2} frames 1080p"
        else:
            source = data / f"jpegs_{size}"
            if not source.exists():
                with publish_folder(source) as staging:
                    make_jpegs(staging, size // 2, rng)
            label = f"{size // 2} JPEGs of 2 MP"
        for workers in (None, 2):
            row = run([str(source)], data, workers) | {"collection": label}
            rows.append(row)
            print(f"{label}, workers {row['workers']}: {row}", flush=True)
    made = table("palette-decompose ... -o NAME.zarr", [
        "collection", "workers", "Mpx", "pass 1 s", "palette s", "pass 2 s", "MP/s",
        "peak RSS MB", "store MB"], [
        [r["collection"], r["workers"], round(r["mpx"]), round(r["pass1_s"], 1),
         round(r["palette_s"], 2), round(r["pass2_s"], 1),
         round(r["mpx"] / (r["pass1_s"] + r["palette_s"] + r["pass2_s"]), 1),
         round(r["rss_mb"]), round(r["store_mb"])] for r in rows])
    write_result("collection", "Collections beyond memory", [made], {"rows": rows})
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plot(rows, out)


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.6))
    for workers, style in ((1, "o-"), (2, "s--")):
        mine = [r for r in rows if r["workers"] == workers]
        total = [r["pass1_s"] + r["palette_s"] + r["pass2_s"] for r in mine]
        left.plot([r["mpx"] for r in mine], total, style, label=f"{workers} process(es)")
        right.plot([r["mpx"] for r in mine], [r["rss_mb"] for r in mine], style,
                   label=f"{workers} process(es) (main process)")
    for ax, label in ((left, "wall time (s)"), (right, "peak RSS (MB)")):
        ax.set_xscale("log")
        ax.set_xlabel("collection size (megapixels)")
        ax.set_ylabel(label)
        ax.legend(fontsize=7)
    left.set_yscale("log")
    right.set_ylim(0, 1.2 * max(r["rss_mb"] for r in rows))
    fig.suptitle("Streaming decomposition: time grows with the collection, memory does not")
    fig.tight_layout()
    fig.savefig(out / "collection_growth.png", dpi=120)
    print(f"saved {out / 'collection_growth.png'}")


if __name__ == "__main__":
    main()
