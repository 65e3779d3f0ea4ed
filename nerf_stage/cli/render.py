"""``nerf-stage render`` and ``eval``: a run's views, recoloured
(``editing.render_edits``) and scored (``evaluation.evaluate_run``)."""

from __future__ import annotations

from pathlib import Path

from ..train.config import BAKE_FACTOR


def add_render(commands) -> None:
    render = commands.add_parser(
        "render", help="render a run's weights once, then recolour them by palettes",
        description="Render the weights of the test views (or an orbit) once into "
                    "DIR/render.npz, then recolour them: DIR/<palette file stem> for each "
                    "--palette, DIR/harmonized-<template> for each --harmonize, DIR/original "
                    "when neither is given; an orbit also gives one GIF each. A later call on "
                    "the same DIR and views reuses render.npz without running the network.")
    render.add_argument("rundir", metavar="RUNDIR")
    render.add_argument("--palette", action="append", default=[], metavar="JSON",
                        help="palette file of the run's K colours (repeatable)")
    render.add_argument("--harmonize", action="append", default=[], metavar="TEMPLATE",
                        help="harmonise the palette with a hue template (repeatable)")
    views = render.add_mutually_exclusive_group()
    views.add_argument("--split", choices=("train", "val", "test"), default="test",
                       help="dataset views to render (default test)")
    views.add_argument("--orbit", type=int, metavar="N", default=None,
                       help="render a turntable of N views instead")
    render.add_argument("--baked", nargs="?", type=int, const=BAKE_FACTOR, metavar="FACTOR",
                        help="render through the colour part baked into a grid FACTOR (default "
                             f"{BAKE_FACTOR}) times finer than the field's (grid runs "
                             "with per-sample diffuse colours: no network, faster)")
    render.add_argument("--region", action="append", default=[], metavar="REGION",
                        help="apply the palettes inside this region only (repeatable; a pixel "
                             "in any is in): box:x0,y0,z0,x1,y1,z1 or ellipsoid:cx,cy,cz,rx,ry,rz "
                             "in world coordinates, colour:K[,T] (the pixels whose weight for "
                             "palette colour K is at least T, 0.5), or a JSON file with "
                             "\"regions\" (docs/selections.md)")
    render.add_argument("-o", "--output", required=True, metavar="DIR")
    render.add_argument("--force", action="store_true",
                        help="overwrite existing outputs (and a render.npz of other views)")
    render.set_defaults(run=run_render)


def add_eval(commands) -> None:
    evaluate = commands.add_parser(
        "eval", help="PSNR and SSIM of a run on the test views",
        description="PSNR and SSIM (scikit-image) of the RGB reconstructed through the "
                    "weights against the test images; for simulated transport scenes also of "
                    "an edited palette against the scene re-simulated with it.")
    evaluate.add_argument("rundir", metavar="RUNDIR")
    evaluate.add_argument("--palette", metavar="JSON", default=None,
                          help="edit to check on simulated scenes (default: the palette rolled "
                               "by one)")
    evaluate.add_argument("--baked", nargs="?", type=int, const=BAKE_FACTOR, metavar="FACTOR",
                          help="score the baked render (render --baked) instead of the network's")
    evaluate.set_defaults(run=run_eval)


def run_render(args) -> int:
    from ..edit.editing import RENDER_FILE, render_edits
    from ..edit.regions import parse_region

    regions = [region for text in args.region for region in parse_region(text)]
    done = render_edits(args.rundir, args.output, args.palette, args.harmonize, args.split,
                        args.orbit, args.force, baked=args.baked, regions=regions)
    if done.reused:
        print(f"recoloured the saved weight render {Path(args.output) / RENDER_FILE} "
              "(the network does not run)")
    where = f" (inside {len(regions)} region{'s' * (len(regions) > 1)})" if regions else ""
    print(f"wrote {', '.join(done.labels)} ({done.views} views) to {args.output}{where}")
    return 0


def run_eval(args) -> int:
    from ..edit.evaluation import evaluate_run
    from ..fields import RGB

    run, scores = evaluate_run(args.rundir, args.palette, args.baked)
    rec = scores["reconstruction"]
    what = "RGB NeRF" if run.kind == RGB else "RGB through the weights"
    print(f"{scores['views']} test views, {scores['seconds_per_view']:.2f} s per view")
    print(f"{what}: PSNR {rec['psnr']:.2f} dB, SSIM {rec['ssim']:.4f}")
    if "off_ring" in scores:
        off = scores["off_ring"]
        print(f"{off['views']} test views off the training rig: PSNR {off['psnr']:.2f} dB, "
              f"SSIM {off['ssim']:.4f}")
    if "edit" in scores:
        edit = scores["edit"]
        print(f"edited palette vs re-simulated scene: PSNR {edit['psnr']:.2f} dB, "
              f"SSIM {edit['ssim']:.4f} (recolouring {scores['recolour_seconds_per_view']:.2e} "
              "s per view)")
    return 0
