"""What the studio's browser draws against what ``nerf-stage render`` makes from the same
camera (issue 54's bound: within 0.3 dB PSNR).

The studio opens RUN in headless Chromium (software WebGL) at ``--window``; from the home
camera (the first training camera) the page's viewport is read once the splats have
arrived, and the run renders the same camera (pose from the browser, its field of view, the
viewport's size) through ``SceneTarget.render``, recoloured as ``nerf-stage render`` does.
Drawn twice: with the splats' weights evaluated for the camera (what the studio sends) and
with their editable weights only (the view-dependent residual dropped). For a splat run
both use the run's own splats; for a grid run, its bake. Scored page against render at the
viewport's size, and each against the home camera's training photo after a box filter to
the photo's size (the issue's bound compares these two).

    python benchmarks/bench_studio_fidelity.py --run RUN [--out benchmarks/out]
        [--window 800x480]

Writes ``benchmarks/results/studio_fidelity.json`` and ``OUT/studio_fidelity.png`` (per
row: the page, the render, the error x4).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from results import table, write_result  # noqa: E402

from nerf_stage.train.metrics import psnr  # noqa: E402
from studio.app import Studio  # noqa: E402
from studio.pictures import camera_pose  # noqa: E402
from studio.scene import SceneTarget, recoloured  # noqa: E402
from tests import browser  # noqa: E402

SETTLE_S = 3.0  # the splats arrive, are sorted and drawn
#: Hides the page's notifications (software WebGL's warning sits over the viewport).
_NO_NOTICES = """
const style = document.createElement('style');
style.textContent = '[class*="Notification"] {display: none !important}';
document.head.appendChild(style);
"""


def page_and_render(driver, target: SceneTarget) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) float the studio's viewport showing ``target``'s splats from the home
    camera, and ``target``'s render of the camera the browser reports, at the viewport's
    size, both cropped about their centre to the training camera's aspect."""
    studio = Studio(target, port=0)
    try:
        driver.get(studio.url)
        browser.wait_for(lambda: studio.view.viewports or None, timeout=120)
        driver.execute_script(_NO_NOTICES)
        time.sleep(SETTLE_S)
        canvas = browser.viewport(driver)
        x, y = (round(v) for v in (canvas.location["x"], canvas.location["y"]))
        w, h = canvas.size["width"], canvas.size["height"]
        page = browser.screenshot(driver)[y:y + h, x:x + w] / 255.0
        client = next(iter(studio.view.viewports.values())).client
        pose = camera_pose(client.camera)
    finally:
        studio.stop()
    render = recoloured(target.render(pose, target.intrinsics(w / h, h)), target.palette, [])[0]
    trained = target.run.intrinsics
    width = min(w, round(h * trained.width / trained.height))
    crop = slice((w - width) // 2, (w - width) // 2 + width)
    return page[:, crop], render[:, crop]


def at_training_size(image: np.ndarray, target: SceneTarget) -> np.ndarray:
    """``image`` box-filtered to the training camera's size."""
    size = (target.run.intrinsics.width, target.run.intrinsics.height)
    picture = Image.fromarray((image * 255).round().astype(np.uint8))
    return np.asarray(picture.resize(size, Image.Resampling.BOX)) / 255.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a nerf-stage train run folder")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/out"))
    parser.add_argument("--window", default="800x480", help="browser window, WIDTHxHEIGHT")
    args = parser.parse_args()
    if not (browser.CHROMIUM and browser.CHROMEDRIVER):
        sys.exit(browser.MISSING)
    target = SceneTarget.open(args.run)
    if target.splats is None:
        sys.exit(f"{args.run}: no splats to draw")
    args.out.mkdir(parents=True, exist_ok=True)
    driver = browser.chromium(*map(int, args.window.split("x")))
    dataset = target.run.dataset()
    truth = dataset.images[dataset.indices("train")[0]]  # the home camera's photo
    results, rows = {"run": str(args.run), "splats": len(target.splats)}, []
    try:
        for name, splats in (("per camera", target.splats),
                             ("editable weights only", replace(target.splats, residual=None))):
            page, render = page_and_render(driver, SceneTarget(
                target.run, target.path, splats, target.home, target.up))
            small = [at_training_size(image, target) for image in (page, render)]
            results[name] = {"page_vs_render": psnr(page, render), "size": page.shape[:2],
                             "page_vs_truth": psnr(small[0], truth),
                             "render_vs_truth": psnr(small[1], truth)}
            print(f"{name:>22}: page against render {results[name]['page_vs_render']:.2f} dB "
                  f"({page.shape[1]}x{page.shape[0]}); against the photo, at its size: page "
                  f"{results[name]['page_vs_truth']:.2f}, render "
                  f"{results[name]['render_vs_truth']:.2f} dB", flush=True)
            rows.append(np.concatenate([page, render, np.clip(4 * np.abs(page - render), 0, 1)],
                                       1))
    finally:
        driver.quit()
    made = table(f"{results['splats']} splats at {args.window} (PSNR dB)",
                 ["splats' weights", "page against render", "page against the photo",
                  "render against the photo"],
                 [[name, round(r["page_vs_render"], 2), round(r["page_vs_truth"], 2),
                   round(r["render_vs_truth"], 2)] for name, r in results.items()
                  if isinstance(r, dict)])
    write_result("studio_fidelity", "What the studio draws against nerf-stage render", [made],
                 results)
    Image.fromarray((np.concatenate(rows) * 255).round().astype(np.uint8)).save(
        args.out / "studio_fidelity.png")
    print(f"picture in {args.out}/studio_fidelity.png (page | render | error x4)")


if __name__ == "__main__":
    main()
