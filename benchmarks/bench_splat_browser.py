"""Splats in the browser (issue 40): the studio page's frame rate against splat count beside
viser's bare splat view of the same splats, in one run, and a palette edit of a bake.

Headless Chromium at 1280x800 draws with software WebGL (SwiftShader), the limit on a
machine without a GPU. For each count, random splats inside the run's occupied bounds are
shown by a bare ``viser`` server holding only them and by ``palette-studio``'s scene mode
(its panel, its pickers) holding the same splats, in turn, ``--repeats`` times. While the
server turns every tab's camera around the scene (20 updates a second, as a drag would),
the page counts its animation frames for ``--seconds`` (and at least 8 frames); the
studio's median rate over the bare viewer's is the ratio the issue bounds (>= 0.8). Each
rate comes with where a frame went (``frame_rate``): the page's drawing and sort, and the
CPU time of Chromium's GPU process, whose software rasteriser is the limit here. For each
of ``--edit-counts``, random splats with a view-dependent residual are opened in the
studio and a colour is typed ``-n`` times: the server's part of each edit (the colours of
every splat computed for the tab's camera and handed to viser, which sends them). Then the
run's own splats (a grid run's bake, ``nerf-stage bake``'s defaults, kept in the run
folder) are opened, their frame rate measured the same way, and a colour is typed ``-n``
times: the server's part and the time from Enter to the first frame whose centre changed.

    python benchmarks/bench_splat_browser.py [--run demo_out/nerf/run] [--out benchmarks/out]
        [--counts 10000 30000 50000 100000] [--seconds 4] [--repeats 3] [-n 10]
        [--edit-counts 300000] [--window 1280x800]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_studio import dominant_colour, summary, time_edits  # noqa: E402
from results import table, write_result  # noqa: E402

from nerf_stage.splats import Splats, render_splats  # noqa: E402
from palette_core.basis import n_terms  # noqa: E402
from studio.app import Studio  # noqa: E402
from studio.scene import SceneTarget  # noqa: E402
from studio.scene_view import look_from_home  # noqa: E402
from tests import browser  # noqa: E402

#: Installed before the page's own scripts: counts animation frames from the next call of
#: ``__frames.start()`` and times where a frame goes on the page's side: the main thread's
#: time in animation-frame callbacks (three.js drawing the scene: its WebGL calls, which
#: wait when the GPU process is behind) and the round trips of messages to its workers
#: (viser sorts the splats by depth in one).
_PROBE = """
const counter = {};
counter.start = () => Object.assign(counter, {n: 0, since: performance.now(), callbacks: 0,
                                              trips: 0, tripMs: 0});
counter.rate = () => 1000 * counter.n / (performance.now() - counter.since);
counter.start();
const request = window.requestAnimationFrame.bind(window);
window.requestAnimationFrame = callback => request(time => {
  const start = performance.now();
  try { callback(time); } finally { counter.callbacks += performance.now() - start; }
});
const Base = window.Worker;
window.Worker = class extends Base {
  constructor(...args) {
    super(...args);
    this.addEventListener('message', () => {
      if (this.sent) { counter.trips++; counter.tripMs += performance.now() - this.sent; }
      this.sent = 0;
    });
  }
  postMessage(...args) { this.sent = this.sent || performance.now(); super.postMessage(...args); }
};
(function tick() { counter.n++; request(tick); })();
window.__frames = counter;
"""
TURNS_PER_SECOND = 20


def random_splats(target: SceneTarget, count: int, rng: np.random.Generator,
                  residual: bool = False) -> Splats:
    """``count`` splats inside the occupied bounds of ``target``'s run, each a few
    thousandths of them wide; with ``residual``, a small view-dependent residual of degree 3
    as a splat run trains (the studio then colours them for each tab's camera)."""
    run, bounds = target.run, target.bounds
    size = float(np.ptp(bounds, 0).max())
    q = rng.normal(size=(count, 4))
    m = n_terms(len(run.palette), run.basis, run.order)
    rest = rng.normal(0, 0.01, (count, 15, m)).astype(np.float32) if residual else None
    return Splats(rng.uniform(*bounds, (count, 3)).astype(np.float32),
                  rng.uniform(0.002, 0.008, (count, 3)).astype(np.float32) * size,
                  (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                  rng.uniform(0.3, 0.9, count).astype(np.float32),
                  rng.dirichlet(np.ones(m), count).astype(np.float32), run.palette, run.basis,
                  run.order, np.ones(3), {}, rest)


def frame_rate(driver, server, centre: np.ndarray, seconds: float, frames: int = 8) -> dict:
    """Frames a second the page drew while the server turned its cameras around ``centre``,
    over at least ``seconds`` and ``frames`` frames (at most a minute), and where a frame
    went, in ms a frame: ``callbacks``, the main thread drawing, and ``sort``, a worker
    message's round trip (``_PROBE``); the CPU time of Chromium's GPU process (SwiftShader
    rasterising) and of its renderers (the page's threads, the sort among them)."""
    clients = browser.wait_for(lambda: list(server.get_clients().values()) or None)
    time.sleep(1.0)  # the first frames, the splats' upload and sort
    cpu = {kind: _cpu_seconds(kind) for kind in ("gpu-process", "renderer")}
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
    fps, n, callbacks, trips, trip_ms = driver.execute_script(
        "const c = window.__frames; return [c.rate(), c.n, c.callbacks, c.trips, c.tripMs]")
    cpu = {kind: 1000 * (_cpu_seconds(kind) - spent) / max(n, 1) for kind, spent in cpu.items()}
    return {"fps": fps, "frame_ms": 1000 / fps, "callbacks_ms": callbacks / max(n, 1),
            "sort_ms": trip_ms / max(trips, 1), "sorts": trips,
            "gpu_process_cpu_ms": cpu["gpu-process"], "renderer_cpu_ms": cpu["renderer"]}


def _cpu_seconds(kind: str) -> float:
    """CPU seconds (user and system) spent so far by Chromium's processes of ``--type=kind``
    (Linux's /proc)."""
    total = 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError):
            if f"--type={kind}".encode() in (stat.parent / "cmdline").read_bytes().replace(
                    b"\0", b" ").split():  # Chromium rewrites its argv, spaces between
                fields = stat.read_text().rsplit(")", 1)[1].split()
                total += int(fields[11]) + int(fields[12])  # utime, stime
    return total / os.sysconf("SC_CLK_TCK")


def bare_rate(driver, splats: Splats, target: SceneTarget, seconds: float) -> dict:
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


def studio_rate(driver, target: SceneTarget, seconds: float) -> dict:
    """The frame rate of palette-studio's scene mode drawing ``target``'s splats."""
    studio = Studio(target, port=0)
    try:
        driver.get(studio.url)
        return frame_rate(driver, studio.server, target.centre, seconds)
    finally:
        studio.stop()


def server_edits(driver, target: SceneTarget, n: int) -> list[float]:
    """The server's part (ms) of ``n`` palette edits typed into the studio page showing
    ``target``'s splats: their colours for the tab's camera computed and handed to viser.
    The page is not waited for: at such counts software WebGL draws a frame in seconds."""
    studio = Studio(target, port=0)
    try:
        driver.get(studio.url)
        browser.wait_for(lambda: studio.view.viewports or None)
        time.sleep(3)  # the splats arrive
        original = np.round(255 * studio.editor.palette[0]).astype(int)
        server = []
        for i in range(n):
            colour = 255 - original if i % 2 == 0 else original
            studio.last_redraw_ms = float("nan")
            browser.type_colour(driver, "colour 1", "#{:02x}{:02x}{:02x}".format(*colour))
            if not browser.wait_for(lambda: not np.isnan(studio.last_redraw_ms), timeout=60):
                raise RuntimeError("the studio did not redraw within 60 s of an edit")
            server.append(studio.last_redraw_ms)
            time.sleep(0.3)
        return server
    finally:
        studio.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default="demo_out/nerf/run", help="a nerf-stage run folder")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out"))
    parser.add_argument("--counts", type=int, nargs="*", default=[10_000, 30_000, 50_000,
                                                                  100_000])
    parser.add_argument("--seconds", type=float, default=4.0, help="frames counted this long")
    parser.add_argument("--repeats", type=int, default=3,
                        help="bare viewer and studio measured in turn this many times (medians)")
    parser.add_argument("-n", type=int, default=10, help="palette edits timed")
    parser.add_argument("--edit-counts", type=int, nargs="+", default=[300_000],
                        help="random splats (with a view-dependent residual) whose palette "
                             "edits' server part is timed")
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
    driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": _PROBE})
    print(f"headless Chromium, window {width}x{height}, software WebGL")
    results = {"counts": {}}
    try:
        for count in args.counts:
            splats = random_splats(baked, count, rng)
            ours_target = SceneTarget(baked.run, baked.path, splats, baked.home)
            bare, ours = both_rates(driver, splats, ours_target, args)
            results["counts"][count] = {"bare": bare, "studio": ours}
            print(f"{count:>7} random splats: {compared(bare, ours)}", flush=True)
        results["edits"] = {}
        for count in args.edit_counts:
            splats = random_splats(baked, count, rng, residual=True)
            server = server_edits(driver, SceneTarget(baked.run, baked.path, splats,
                                                      baked.home), args.n)
            results["edits"][count] = server
            print(summary(f"{count} random splats, palette edit: server (ms)", server, 20),
                  flush=True)
        results.update(bake(driver, baked, args))
    finally:
        driver.quit()
    rates = table("frames a second while the camera turns (medians)",
                  ["splats", "bare viser fps", "studio fps", "studio / bare"],
                  [[count, round(r["bare"]["fps"], 2), round(r["studio"]["fps"], 2),
                    round(r["studio"]["fps"] / r["bare"]["fps"], 2)]
                   for count, r in results["counts"].items()])
    edits = table("a palette edit's server part (ms)", ["splats", "median", "p90"],
                  [[count, round(float(np.median(ms)), 2),
                    round(float(np.percentile(ms, 90)), 2)]
                   for count, ms in results["edits"].items()])
    write_result("splat_browser", "Splats in the browser", [rates, edits], results)
    print(f"{args.out}/studio_splats.png: the page "
          "drawn by the network, then by the splats, from the home camera")


def both_rates(driver, splats: Splats, target: SceneTarget, args) -> tuple[dict, dict]:
    """The bare viewer's and the studio's ``frame_rate`` measurements, taken in turn
    ``--repeats`` times: each the median of its runs, key by key, with the runs' rates."""
    runs = [(bare_rate(driver, splats, target, args.seconds),
             studio_rate(driver, target, args.seconds)) for _ in range(args.repeats)]
    return tuple({**{key: float(np.median([m[key] for m in page])) for key in page[0]},
                  "fps_runs": [m["fps"] for m in page]} for page in zip(*runs))


def compared(bare: dict, ours: dict) -> str:
    """Both pages' frame rates, their ratio (the issue's target) and a frame's breakdown
    (medians of the repeats)."""
    def frame(m):
        return (f"{m['fps']:4.1f} fps (of {min(m['fps_runs']):.1f}-{max(m['fps_runs']):.1f}; "
                f"{m['frame_ms']:5.0f} ms a frame: drawing "
                f"{m['callbacks_ms']:4.0f}, sort round trip {m['sort_ms']:4.0f}; CPU: GPU "
                f"process {m['gpu_process_cpu_ms']:4.0f}, page {m['renderer_cpu_ms']:4.0f})")
    return (f"bare viser {frame(bare)}, studio {frame(ours)}, ratio "
            f"{ours['fps'] / bare['fps']:.2f} (target >= 0.8)")


def bake(driver, target: SceneTarget, args) -> dict:
    """The run's own bake in the studio: its frame rate, palette edits timed, and the page
    drawn by the network (before splats) and by the splats from the home camera."""
    splats = target.splats
    bare, ours = both_rates(driver, splats, target, args)
    print(f"the run's bake, {len(splats)} splats: {compared(bare, ours)}")
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
        index = dominant_colour(studio.editor.palette, weights[0], splats.basis, splats.order)
        page, server = time_edits(driver, studio, index, args.n)
        print(summary("palette edit -> new frame (ms)", page))
        print(summary(f"  server: {len(splats)} splats' colours computed, sent (ms)", server,
                      20))
    finally:
        studio.stop()
    Image.fromarray(np.concatenate([before, after], 1)).save(args.out / "studio_splats.png")
    return {"bake": {"splats": len(splats), "bare": bare, "studio": ours,
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
