"""palette-studio latency in a real browser (headless Chromium, software WebGL).

Photo mode: a 1-megapixel photo (a mosaic of scikit-image photos, as in
bench_collection.py) decomposed with K = 6. Scene mode: a trained weight NeRF
(default `demo_out/nerf/run` from `make demo`, 100x100 views), drawn by the network
(bench_splat_browser.py times the splats). For each, a colour
is typed into the panel N times (alternating between the dominant colour of the
viewport's centre and its complement) and the page times, frame by frame, Enter to
the first frame whose centre pixel changed (tests/browser.py). Photo mode also times brush
dabs: with colour 1 edited inside a small dab in a corner, a dab clicked at the centre,
from the click's release to the first frame whose centre changed, and the server's part
(the dab painted, the image recoloured and sent). Scene mode also times a camera move to
the refined view sent to the browser. Saves a screenshot of each mode.

    python benchmarks/bench_studio.py [--run demo_out/nerf/run] [--out benchmarks/out] [-n 20]
                                      [--window 1280x800]

Software WebGL (SwiftShader) draws every frame on the CPU, so the browser's share
of the latency grows with the window; the server's share is printed apart.

Targets (issue 17): photo <= 100 ms, scene view <= 50 ms, refined view <= 1 s; (issue 41)
a brush dab no slower than a palette edit, its server part <= 50 ms.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_collection import mosaic, photos  # noqa: E402
from results import table, write_result  # noqa: E402

from palette_core.basis import Basis, basis_terms  # noqa: E402
from palette_core.decompose import decompose  # noqa: E402
from studio.app import Studio  # noqa: E402
from studio.photos import PhotoTarget  # noqa: E402
from studio.pictures import camera_pose, to_bytes  # noqa: E402
from studio.scene import SceneTarget  # noqa: E402
from tests import browser  # noqa: E402


def photo_stack(folder: Path) -> Path:
    """A 1224 x 816 (1.0 MP) photo mosaic and its weight stack."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    image = folder / "mosaic.png"
    Image.fromarray(mosaic(np.random.default_rng(0), photos(), 816, 1224)).save(image)
    stack = folder / "mosaic.npz"
    decompose([image], k=6).write(stack, force=True)
    return stack


def dominant_colour(palette: np.ndarray, weights: np.ndarray, basis: Basis = Basis.ADDITIVE,
                    order: int = 1) -> int:
    """The colour of ``palette`` (K, 3) whose edit to its complement changes the centre of a
    (H, W, M) view of ``weights`` most (in a transport basis, pairs of colours light a pixel
    too: its largest additive weight may not be the colour that shows)."""
    h, w = weights.shape[:2]
    centre, terms = weights[h // 2, w // 2], basis_terms(palette, basis, order)
    changes = []
    for k in range(len(palette)):
        edited = np.array(palette, np.float64)
        edited[k] = 1 - edited[k]
        changes.append(np.abs(centre @ (basis_terms(edited, basis, order) - terms)).sum())
    return int(np.argmax(changes))


def time_edits(driver, studio: Studio, index: int, n: int) -> tuple[list[float], list[float]]:
    """Type colour ``index`` n times; browser latencies (ms) and server redraws (ms)."""
    browser.watch_centre(driver)
    original = to_bytes(studio.editor.palette[index])
    page, server = [], []
    for i in range(n):
        colour = 255 - original if i % 2 == 0 else original
        browser.type_colour(driver, f"colour {index + 1}", "#{:02x}{:02x}{:02x}".format(*colour))
        latency = browser.change_latency(driver)
        if latency is None:
            raise RuntimeError("the viewport did not change within 10 s")
        page.append(latency)
        server.append(studio.last_redraw_ms)
        time.sleep(0.3)
    return page, server


def time_dabs(driver, studio: Studio, index: int, n: int) -> tuple[list[float], ...]:
    """Brush dabs at the centre, n times, each after the selection was reset to a dab in a
    corner (colour ``index`` edited to its complement); browser latencies, the server's part,
    and the time from asking selenium for the click to its arrival at the server (ms)."""
    view = studio.view
    arrived = []
    clicked = view._clicked

    def arrival(event) -> None:
        arrived.append(time.perf_counter())
        clicked(event)

    view._clicked = arrival  # registered by the tool below
    complement = to_bytes(1 - studio.editor.palette[index])
    browser.type_colour(driver, f"colour {index + 1}", "#{:02x}{:02x}{:02x}".format(*complement))
    view.tool.value = "brush"
    time.sleep(1)  # the page learns that clicks now paint
    page, server, to_server = [], [], []
    for _ in range(n):
        with studio.lock:
            view.drawing.clear()
            view.drawing.dab(view.image, np.array([5.0, 5.0]), 4, 0)
            studio.redraw()
        time.sleep(0.5)
        browser.watch_centre(driver)
        start = time.perf_counter()
        browser.click(driver, 0.5, 0.5)
        latency = browser.change_latency(driver)
        if latency is None:
            raise RuntimeError("the viewport did not change within 10 s")
        page.append(latency)
        server.append(view.last_selection_ms)
        to_server.append(1000 * (arrived[-1] - start))
    view.tool.value = "everywhere"
    return page, server, to_server


def latency(rows: list, name: str, values: list[float], target: float | None = None) -> None:
    """Print ``summary`` and add its row (median, p90, max, target) to ``rows``."""
    print(summary(name, values, target))
    values = np.asarray(values)
    rows.append([name.strip(), round(float(np.median(values)), 1),
                 round(float(np.percentile(values, 90)), 1), round(float(values.max()), 1),
                 f"<= {target:g}" if target else ""])


def summary(name: str, values: list[float], target: float | None = None) -> str:
    values = np.asarray(values)
    line = (f"{name:<44} median {np.median(values):7.1f}   p90 {np.percentile(values, 90):7.1f}"
            f"   max {values.max():7.1f}")
    return line + (f"   (target <= {target:g})" if target else "")


def bench_photos(driver, out: Path, n: int) -> list:
    target = PhotoTarget.open(photo_stack(out / "studio"))
    studio = Studio(target, port=0)
    try:
        driver.get(studio.url)
        browser.wait_for(lambda: browser.pixel(driver) not in (None, [0, 0, 0]))
        time.sleep(2)
        index = dominant_colour(studio.editor.palette, target.weights(0))
        page, server = time_edits(driver, studio, index, n)
        h, w = target.weights(0).shape[:2]
        rows = []
        latency(rows, f"photo {w}x{h}: change -> new frame (ms)", page, 100)
        latency(rows, "  of which server recolour + encode (ms)", server)
        page, server, to_server = time_dabs(driver, studio, index, n)
        latency(rows, f"photo {w}x{h}: brush dab -> new frame (ms)", page)
        latency(rows, "  selenium click -> at the server (ms)", to_server)
        latency(rows, "  server paint + recolour + encode (ms)", server, 50)
        driver.save_screenshot(str(out / "studio_photos.png"))
    finally:
        studio.stop()
    return rows


def bench_scene(driver, run: Path, out: Path, n: int) -> list:
    target = SceneTarget.open(run, bake=False)
    studio = Studio(target, port=0)
    try:
        driver.get(studio.url)
        rows = target.run.intrinsics.height
        view = browser.wait_for(lambda: next(iter(studio.view.viewports.values()), None))
        browser.wait_for(lambda: view.drawn[0] == rows, timeout=60)
        time.sleep(2)
        index = dominant_colour(studio.editor.palette, view.render.weights[0],
                                target.run.basis, target.run.order)
        page, server = time_edits(driver, studio, index, n)
        h, w = view.render.weights.shape[1:3]
        rows = []
        latency(rows, f"scene {w}x{h}: change -> new frame (ms)", page, 50)
        latency(rows, "  of which server recolour + encode (ms)", server)
        driver.save_screenshot(str(out / "studio_scene.png"))
        refined = []
        pose = camera_pose(view.client.camera)
        for i in range(n):
            angle = np.radians(4 * (i + 1))
            moved = pose[:3, 3] - target.centre
            turn = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0],
                             [-np.sin(angle), 0, np.cos(angle)]])
            start = time.perf_counter()
            with view.client.atomic():
                view.client.camera.position = target.centre + turn @ moved
                view.client.camera.look_at = target.centre
            if not browser.wait_for(lambda since=start: view.drawn[0] == rows
                                    and view.drawn[1] > since, timeout=30):
                raise RuntimeError("no refined view within 30 s")
            refined.append(view.drawn[1] - start)
        latency(rows, "scene: camera moved -> refined view sent (s)", refined, 1)
    finally:
        studio.stop()
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default="demo_out/nerf/run", help="a nerf-stage run folder")
    parser.add_argument("--out", default="benchmarks/out")
    parser.add_argument("-n", type=int, default=20, help="edits (and camera moves) timed")
    parser.add_argument("--window", default="1280x800", help="browser window, WIDTHxHEIGHT")
    args = parser.parse_args()
    width, height = map(int, args.window.split("x"))
    if not (browser.CHROMIUM and browser.CHROMEDRIVER):
        sys.exit(browser.MISSING)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    driver = browser.chromium(width, height)
    print(f"headless Chromium, window {width}x{height}")
    try:
        rows = bench_photos(driver, out, args.n)
        if Path(args.run).is_dir():
            rows += bench_scene(driver, Path(args.run), out, args.n)
        else:
            print(f"no run at {args.run}: scene mode skipped (make demo trains one)")
    finally:
        driver.quit()
    made = table(f"{args.n} edits in headless Chromium at {args.window}",
                 ["measured", "median", "p90", "max", "target"], rows)
    write_result("studio", "The studio's latency in a browser", [made], {"rows": rows})
    print(f"screenshots in {out}/studio_*.png")


if __name__ == "__main__":
    main()
