"""Splats in the browser (issue 40): the studio page's frame rate against splat count beside
viser's bare splat view of the same splats, in one run, and a palette edit of a bake.

Headless Chromium at 1280x800 draws with software WebGL (SwiftShader), the limit on a
machine without a GPU. For each count, random splats inside the run's occupied bounds are
shown twice: by a bare ``viser`` server holding only them, and by ``palette-studio``'s scene
mode (its panel, its pickers) holding the same splats. While the server turns every tab's
camera around the scene (20 updates a second, as a drag would), the page counts its
animation frames for ``--seconds`` (and at least 8 frames); the studio's rate over the
bare rate is the ratio the issue bounds (>= 0.8). Then the run's own bake (``nerf-stage
bake``'s defaults, kept in the run folder) is opened, its frame rate measured the same way,
and a colour is typed ``-n``
times: the server's part (the colours of every splat computed and handed to viser, which
sends them) and the time from Enter to the first frame whose centre changed.

    python benchmarks/bench_splat_browser.py [--run demo_out/nerf/run] [--out benchmarks/out]
        [--counts 10000 30000 50000 100000] [--seconds 4] [-n 10] [--window 1280x800]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_studio import dominant_colour, summary, time_edits  # noqa: E402

from nerf_stage.splats import Splats, render_splats  # noqa: E402
from palette_core.basis import n_terms  # noqa: E402
from studio.app import Studio  # noqa: E402
from studio.scene import SceneTarget  # noqa: E402
from studio.scene_view import look_from_home  # noqa: E402
from tests import browser  # noqa: E402

#: Animation frames the page draws, counted from the next call of ``__frames.start()``.
_COUNT_FRAMES = """
const counter = {n: 0, since: performance.now()};
counter.start = () => { counter.n = 0; counter.since = performance.now(); };
counter.rate = () => 1000 * counter.n / (performance.now() - counter.since);
(function tick() { counter.n++; requestAnimationFrame(tick); })();
window.__frames = counter;
"""
TURNS_PER_SECOND = 20


def random_splats(target: SceneTarget, count: int, rng: np.random.Generator) -> Splats:
    """``count`` splats inside the occupied bounds of ``target``'s run, each a few
    thousandths of them wide."""
    run, bounds = target.run, target.bounds
    size = float(np.ptp(bounds, 0).max())
    q = rng.normal(size=(count, 4))
    m = n_terms(len(run.palette), run.basis, run.order)
    return Splats(rng.uniform(*bounds, (count, 3)).astype(np.float32),
                  rng.uniform(0.002, 0.008, (count, 3)).astype(np.float32) * size,
                  (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                  rng.uniform(0.3, 0.9, count).astype(np.float32),
                  rng.dirichlet(np.ones(m), count).astype(np.float32), run.palette, run.basis,
                  run.order, np.ones(3), {})


def frame_rate(driver, server, centre: np.ndarray, seconds: float, frames: int = 8) -> float:
    """Frames a second the page drew while the server turned its cameras around ``centre``,
    over at least ``seconds`` and ``frames`` frames (at most a minute)."""
    driver.execute_script(_COUNT_FRAMES)
    clients = browser.wait_for(lambda: list(server.get_clients().values()) or None)
    time.sleep(1.0)  # the first frames, the splats' upload and sort
    driver.execute_script("window.__frames.start()")
    start = checked = time.perf_counter()
    while (elapsed := time.perf_counter() - start) < 60:
        angle = 2 * np.pi * elapsed / 8  # a turn in 8 s
        for client in clients:
            eye = client.camera.position - centre
            radius = np.hypot(eye[0], eye[2])
            with client.atomic():
                client.camera.position = centre + [radius * np.sin(angle), eye[1],
                                                   radius * np.cos(angle)]
                client.camera.look_at = centre
        time.sleep(1 / TURNS_PER_SECOND)
        if elapsed >= seconds and time.perf_counter() - checked > 1:
            checked = time.perf_counter()
            if driver.execute_script("return window.__frames.n") >= frames:
                break
    return driver.execute_script("return window.__frames.rate()")


def bare_rate(driver, splats: Splats, target: SceneTarget, seconds: float) -> float:
    """The frame rate of a bare viser server that shows ``splats`` and nothing else, from
    the studio's first camera for ``target``."""
    import viser

    with contextlib.redirect_stdout(sys.stderr):  # viser's banner
        server = viser.ViserServer(port=0, verbose=False)
    try:
        server.scene.add_gaussian_splats("/splats", splats.centres, splats.covariances(),
                                         splats.colours(), splats.opacities[:, None])
        server.on_client_connect(lambda client: look_from_home(client.camera, target))
        driver.get(f"http://127.0.0.1:{server.get_port()}")
        return frame_rate(driver, server, target.centre, seconds)
    finally:
        server.stop()


def studio_rate(driver, target: SceneTarget, seconds: float) -> float:
    """The frame rate of palette-studio's scene mode drawing ``target``'s splats."""
    studio = Studio(target, port=0)
    try:
        driver.get(studio.url)
        return frame_rate(driver, studio.server, target.centre, seconds)
    finally:
        studio.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default="demo_out/nerf/run", help="a nerf-stage run folder")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out"))
    parser.add_argument("--counts", type=int, nargs="+", default=[10_000, 30_000, 50_000,
                                                                  100_000])
    parser.add_argument("--seconds", type=float, default=4.0, help="frames counted this long")
    parser.add_argument("-n", type=int, default=10, help="palette edits timed")
    parser.add_argument("--window", default="1280x800", help="browser window, WIDTHxHEIGHT")
    args = parser.parse_args()
    if not (browser.CHROMIUM and browser.CHROMEDRIVER):
        sys.exit(browser.MISSING)
    if not Path(args.run, "config.json").is_file():
        sys.exit(f"no run at {args.run} (make demo trains one; or --run RUN)")
    width, height = map(int, args.window.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    baked = SceneTarget.open(args.run)  # bakes once, then reads RUN/splats.npz
    rng = np.random.default_rng(0)
    driver = browser.chromium(width, height)
    print(f"headless Chromium, window {width}x{height}, software WebGL")
    results = {"counts": {}}
    try:
        for count in args.counts:
            splats = random_splats(baked, count, rng)
            ours_target = SceneTarget(baked.run, baked.path, splats, baked.home)
            bare = bare_rate(driver, splats, ours_target, args.seconds)
            ours = studio_rate(driver, ours_target, args.seconds)
            results["counts"][count] = {"bare_fps": bare, "studio_fps": ours}
            print(f"{count:>7} random splats: bare viser {bare:5.1f} fps, studio {ours:5.1f} fps,"
                  f" ratio {ours / bare:.2f} (target >= 0.8)", flush=True)
        results.update(bake(driver, baked, args))
    finally:
        driver.quit()
    (args.out / "splat_browser.json").write_text(json.dumps(results, indent=1))
    print(f"results in {args.out}/splat_browser.json; {args.out}/studio_splats.png: the page "
          "drawn by the network, then by the splats, from the home camera")


def bake(driver, target: SceneTarget, args) -> dict:
    """The run's own bake in the studio: its frame rate, palette edits timed, and the page
    drawn by the network (before splats) and by the splats from the home camera."""
    splats = target.splats
    bare = bare_rate(driver, splats, target, args.seconds)
    ours = studio_rate(driver, target, args.seconds)
    print(f"the run's bake, {len(splats)} splats: bare viser {bare:5.1f} fps, studio "
          f"{ours:5.1f} fps, ratio {ours / bare:.2f}")
    network = SceneTarget(target.run, target.path, None, target.home)
    before = screenshot(driver, network, lambda studio: next(
        iter(studio.view.viewports.values())).drawn[0] == target.run.intrinsics.height)
    studio = Studio(target, port=0)
    try:
        driver.get(studio.url)
        browser.wait_for(lambda: studio.view.viewports or None)
        time.sleep(3)  # the splats arrive and are sorted
        after = browser.screenshot(driver)
        weights, _ = render_splats(splats, target.home_pose()[None],
                                   target.run.intrinsics)
        page, server = time_edits(driver, studio, dominant_colour(studio, weights[0]), args.n)
        print(summary("palette edit -> new frame (ms)", page))
        print(summary(f"  server: {len(splats)} splats' colours computed, sent (ms)", server,
                      20))
    finally:
        studio.stop()
    Image.fromarray(np.concatenate([before, after], 1)).save(args.out / "studio_splats.png")
    return {"bake": {"splats": len(splats), "bare_fps": bare, "studio_fps": ours,
                     "edit_ms": page, "server_ms": server}}


def screenshot(driver, target: SceneTarget, ready) -> np.ndarray:
    """(H, W, 3) the studio page showing ``target`` once ``ready(studio)``."""
    studio = Studio(target, port=0)
    try:
        driver.get(studio.url)
        browser.wait_for(lambda: studio.view.viewports and ready(studio), timeout=120)
        time.sleep(1)
        return browser.screenshot(driver)
    finally:
        studio.stop()


if __name__ == "__main__":
    main()
