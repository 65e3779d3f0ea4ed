"""``nerf-stage``: simulate scenes or pose photos; train weight NeRFs, render and recolour
them, evaluate.

The torch-based commands import torch only when they run, so ``simulate`` works
without the ``nerf`` extra.
"""

from __future__ import annotations

import sys
from pathlib import Path

from palette_core.cli import ArgumentParser, add_config_arguments, config_from_args, run_cli
from palette_core.errors import InputError
from palette_core.outputs import atomic_outputs, check_outdir, check_writable
from palette_core.palette_file import read_palette_json
from palette_core.stack import DEFAULT_STACK

from .config import BAKE_FACTOR, CONFIG_ENV, TrainConfig
from .simulation import (
    BUILTIN_SCENES,
    LAYOUTS,
    load_scene,
    simulate,
    with_overrides,
    write_dataset,
)

PROG = "nerf-stage"


def build_parser(train_defaults: TrainConfig | None = None) -> ArgumentParser:
    """The parser of every command; ``train``'s flags default to ``train_defaults`` (the
    dataclass's defaults when None)."""
    parser = ArgumentParser(prog=PROG, description="NeRF stage of the palette toolkit.")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                     parser_class=ArgumentParser)
    sim = commands.add_parser(
        "simulate", help="path trace a scene into a Blender-format dataset with transport weights",
        description="Path trace every view of a scene. Writes transforms_{train,val,test}.json, "
                    "RGBA PNGs and, for scenes with editable materials, weights.npz "
                    "(transport basis) and materials.json.")
    sim.add_argument("scene", metavar="SCENE",
                     help=f"a built-in scene ({', '.join(BUILTIN_SCENES)}) or a .json / .toml file")
    sim.add_argument("outdir", metavar="OUTDIR", help="dataset folder to write")
    sim.add_argument("--order", type=int, default=None,
                     help="transport order n to keep (default: the scene's)")
    sim.add_argument("--spp", type=int, default=None, help="paths per pixel (default: the scene's)")
    sim.add_argument("--resolution", type=int, default=None, metavar="PIXELS",
                     help="square image size (default: the scene's)")
    sim.add_argument("--views", type=int, nargs=3, default=None, metavar=("TRAIN", "VAL", "TEST"),
                     help="views per split (default: the scene's)")
    sim.add_argument("--off-ring", type=int, default=None, metavar="N",
                     help="N more test views away from the training rig (above it, closer, "
                          "farther: test/o_<i>.png, marked \"off_ring\" in "
                          "transforms_test.json) to see floaters and holes; blender layout")
    sim.add_argument("--seed", type=int, default=None, help="random seed (default: the scene's)")
    sim.add_argument("--layout", choices=LAYOUTS, default="blender",
                     help="blender (default: transforms_{train,val,test}.json, transport "
                          "weights) or nerfstudio (a capture folder: images/ and "
                          "transforms.json, for palette-decompose images/ and nerf-stage train)")
    sim.add_argument("--force", action="store_true", help="replace a non-empty OUTDIR")
    sim.set_defaults(run=_simulate)
    _add_poses(commands)
    _add_train(commands, train_defaults or TrainConfig())
    _add_render(commands)
    _add_eval(commands)
    _add_bake(commands)
    return parser


def _add_bake(commands) -> None:
    from .splats import MAX_SPLATS, REFINE_STEPS, SPLAT_CACHE

    bake = commands.add_parser(
        "bake", help="bake a run into 3D Gaussian splats that carry palette weights",
        description="Bake a weight NeRF into 3D Gaussians, one where the training views' light "
                    "stops, each with the palette weights of its light, refined against the "
                    "network's renders of the training views (docs/splats.md). A run of the "
                    "splats backbone is written as it was trained (no bake; --max-splats and "
                    "--refine-steps do not apply). Not to be confused with render --baked (the "
                    "colour part baked into a grid).")
    bake.add_argument("rundir", metavar="RUNDIR")
    bake.add_argument("-o", "--output", metavar="FILE.splat.npz",
                      help=f"default RUNDIR/{SPLAT_CACHE}, the bake palette-studio and export "
                           "RUNDIR read")
    bake.add_argument("--max-splats", type=int, default=MAX_SPLATS,
                      help=f"at most this many splats (default {MAX_SPLATS})")
    bake.add_argument("--refine-steps", type=int,
                      help=f"views fitted after the first splats (default "
                           f"{REFINE_STEPS['cpu']} on the CPU, {REFINE_STEPS['cuda']} with "
                           "CUDA; 0: none)")
    bake.add_argument("--force", action="store_true", help="overwrite FILE")
    bake.set_defaults(run=_bake)
    export = commands.add_parser(
        "export", help="write recoloured splats as a 3D Gaussian splatting PLY",
        description="Write the splats of a bake (nerf-stage bake), recoloured with a palette, "
                    "as a binary PLY in the layout 3D Gaussian splatting viewers read.")
    export.add_argument("bake", metavar="FILE.splat.npz|RUNDIR",
                        help=f"a bake, or a run folder: its {SPLAT_CACHE}, baked first when it "
                             "is missing or older than the run")
    export.add_argument("--palette", metavar="JSON", default=None,
                        help="palette file of the run's K colours (default: the run's own)")
    export.add_argument("-o", "--output", required=True, metavar="FILE.ply")
    export.add_argument("--force", action="store_true", help="overwrite FILE.ply")
    export.set_defaults(run=_export)


def _add_poses(commands) -> None:
    from .sfm import CAMERA_MODELS, MAPPERS, MATCHERS

    poses = commands.add_parser(
        "poses", help="camera poses for a folder of photos (structure from motion, pycolmap)",
        description="Estimate the cameras of a folder of photos with COLMAP's structure from "
                    "motion (pycolmap, on the CPU), or convert the COLMAP model a folder "
                    "already holds (sparse/0, text or binary, with its photos in images/). "
                    "Writes a capture folder: images/ and transforms.json (nerfstudio "
                    "layout), undistorted where the camera distorts.")
    poses.add_argument("source", metavar="PHOTOS", help="folder of photos, or of a COLMAP model")
    poses.add_argument("-o", "--output", required=True, metavar="CAPTURE",
                       help="capture folder to write")
    poses.add_argument("--camera-model", choices=CAMERA_MODELS, default="SIMPLE_RADIAL",
                       help="COLMAP camera model shared by the photos (default: SIMPLE_RADIAL; "
                            "SIMPLE_PINHOLE for renders without distortion)")
    poses.add_argument("--matcher", choices=MATCHERS, default="auto",
                       help="pairs to match: every pair, or neighbours in name order (video "
                            "frames); auto (default) matches every pair of up to 150 photos")
    poses.add_argument("--mapper", choices=MAPPERS, default="global",
                       help="global (default: GLOMAP, robust on forward-moving sequences) or "
                            "incremental (COLMAP's classic mapper)")
    poses.add_argument("--force", action="store_true", help="replace a non-empty CAPTURE")
    poses.set_defaults(run=_poses)


def _add_train(commands, defaults: TrainConfig) -> None:
    train = commands.add_parser(
        "train", help="train a weight NeRF on a dataset and its weight stack",
        description="Train a NeRF whose colour head outputs the weight stack's M channels "
                    "(PaletteNeRF). Writes RUNDIR/config.json and RUNDIR/checkpoint.pt. "
                    "Every field of the training config is a flag; their defaults can come "
                    f"from a JSON file named by the environment variable {CONFIG_ENV}.")
    train.add_argument("data", metavar="DATADIR", nargs="?", default=".",
                       help="Blender or nerfstudio dataset folder (default: this folder)")
    train.add_argument("--weights", default=None, metavar="STACK",
                       help="weight stack (.npz) of the training frames (default: "
                            f"DATADIR/{DEFAULT_STACK}, where palette-decompose images/ run in "
                            "DATADIR and nerf-stage simulate put it)")
    train.add_argument("-o", "--output", metavar="RUNDIR", default=None,
                       help="run folder (default: DATADIR-BACKBONE beside DATADIR)")
    train.add_argument("--frames-outside", action="store_true",
                       help="read frames whose file_path lies outside DATADIR (absolute, or "
                            "climbing out with ..); refused by default")
    train.add_argument("--downscale", type=int, default=1, metavar="N",
                       help="train on images N times smaller than the files (the mean of each "
                            "N x N block; the weight stack may be of either size); render and "
                            "eval read them so too (default 1)")
    add_config_arguments(train, defaults)
    again = train.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true", help="continue RUNDIR's checkpoint")
    again.add_argument("--force", action="store_true", help="start RUNDIR afresh")
    train.set_defaults(run=_train)


def _add_render(commands) -> None:
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
    render.set_defaults(run=_render)


def _add_eval(commands) -> None:
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
    evaluate.set_defaults(run=_eval)


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _dispatch(argv))


def _dispatch(argv) -> int:
    argv = sys.argv[1:] if argv is None else argv
    # Only train reads CONFIG_ENV: a bad file there must not break the other commands.
    defaults = TrainConfig.defaults() if argv[:1] == ["train"] else None
    args = build_parser(defaults).parse_args(argv)
    return args.run(args)


def _simulate(args) -> int:
    scene = with_overrides(load_scene(args.scene), order=args.order, spp=args.spp,
                           resolution=args.resolution, views=args.views, seed=args.seed,
                           off_ring=args.off_ring)
    if scene.camera.off_ring and args.layout != "blender":
        raise InputError("off-ring test views are written in the blender layout only (its "
                         "transforms_test.json marks them)")
    check_outdir(args.outdir, args.force)
    sim = simulate(scene)
    spec = args.scene if args.scene in BUILTIN_SCENES else str(Path(args.scene).resolve())
    written = write_dataset(sim, scene, args.outdir, spec, force=args.force, layout=args.layout)
    cam, render = scene.camera, scene.render
    print(f"{scene.name}: {len(sim.names)} views of {cam.width}x{cam.height}, {render.spp} spp, "
          f"{render.light} light" + (f", order {sim.order}" if sim.weights is not None else "")
          + f", traced in {sim.seconds:.1f} s")
    if sim.weights is not None and args.layout == "blender":
        print(f"palette ({len(sim.palette)} editable materials, {sim.weights.shape[-1]} transport "
              f"terms): see {args.outdir}/materials.json")
    print(f"wrote {len(written)} files to {args.outdir}")
    return 0


def _poses(args) -> int:
    from .sfm import estimate_poses

    report = estimate_poses(args.source, args.output, args.camera_model, args.matcher,
                            args.mapper, args.force)
    total = len(report.registered) + len(report.missing)
    print(f"registered {len(report.registered)} of {total} photos: {report.points} points, "
          f"mean reprojection error {report.reprojection_error:.2f} px"
          + (", undistorted" if report.undistorted else "")
          + "".join(f"; {phase} {s:.1f} s" for phase, s in report.seconds.items()))
    if report.missing:
        print(f"not registered (left out of the capture): {', '.join(report.missing)}")
    if len(report.models) > 1:
        print(f"the photos split into {len(report.models)} models of "
              f"{', '.join(map(str, report.models))} photos; the largest is kept")
    print(f"wrote {args.output} (nerfstudio layout); next: palette-decompose "
          f"{Path(args.output) / 'images'} -o {Path(args.output) / DEFAULT_STACK}, then "
          f"{PROG} train {args.output}")
    return 0


def _train(args) -> int:
    from palette_core.stack import read_stack

    from .data import load_dataset
    from .run import CHECKPOINT
    from .trainer import peak_memory, train

    config = config_from_args(TrainConfig, args)
    data = Path(args.data).resolve()
    rundir = Path(args.output or data.with_name(f"{data.name}-{config.backbone}"))
    dataset = load_dataset(data, config.background, args.frames_outside, args.downscale)
    weights = Path(args.weights) if args.weights else data / DEFAULT_STACK
    if args.weights is None and not weights.is_file():
        raise InputError(f"{weights} does not exist: make it with palette-decompose images/ "
                         "in the dataset folder, or give --weights STACK")
    print(f"dataset: {data} ({dataset.layout} layout, {len(dataset.names)} frames, "
          f"{len(dataset.indices('train'))} for training)")
    print(f"weights: {weights.resolve()}", flush=True)
    run = train(config, dataset, read_stack(weights), rundir, resume=args.resume,
                force=args.force, weights_path=str(weights.resolve()))
    log = run.record.log
    limited = " (the --minutes limit)" if len(log) < config.total_iters else ""
    print(f"trained {config.backbone} ({config.strategy}) for {len(log)} iterations in "
          f"{log[-1]['seconds']:.0f} s{limited}, last batch PSNR {log[-1]['psnr']:.2f} dB, "
          f"peak memory {peak_memory(run.device)}")
    print(f"wrote {rundir / CHECKPOINT}; next: {PROG} render {rundir} -o DIR")
    return 0


def _render(args) -> int:
    from .editing import RENDER_FILE, render_edits
    from .regions import parse_region

    regions = [region for text in args.region for region in parse_region(text)]
    done = render_edits(args.rundir, args.output, args.palette, args.harmonize, args.split,
                        args.orbit, args.force, baked=args.baked, regions=regions)
    if done.reused:
        print(f"recoloured the saved weight render {Path(args.output) / RENDER_FILE} "
              "(the network does not run)")
    where = f" (inside {len(regions)} region{'s' * (len(regions) > 1)})" if regions else ""
    print(f"wrote {', '.join(done.labels)} ({done.views} views) to {args.output}{where}")
    return 0


def _bake(args) -> int:
    from .splats import SPLAT_CACHE, bake_run, write_splats

    output = Path(args.output or Path(args.rundir) / SPLAT_CACHE)
    check_writable([output], args.force)
    splats = bake_run(args.rundir, args.max_splats, args.refine_steps)
    with atomic_outputs(args.force) as stage:
        write_splats(splats, stage(output))
    print(f"wrote {len(splats)} splats to {output} ({output.stat().st_size / 2**20:.1f} MB); "
          f"next: {PROG} export {args.output or args.rundir} --palette P.json -o scene.ply")
    return 0


def _export(args) -> int:
    from .run import load_run
    from .splats import cached_bake, read_splats, write_ply

    output = Path(args.output)
    if output.suffix.lower() != ".ply":
        raise InputError(f"a splat export is written as .ply, got {output}")
    check_writable([output], args.force)
    splats = (cached_bake(load_run(args.bake), args.bake) if Path(args.bake).is_dir()
              else read_splats(args.bake))
    palette = (None if args.palette is None
               else read_palette_json(args.palette, k=len(splats.palette)))
    with atomic_outputs(args.force) as stage:
        write_ply(splats, stage(output), palette)
    print(f"wrote {len(splats)} splats to {output}")
    return 0


def _eval(args) -> int:
    from .evaluation import evaluate
    from .fields import RGB
    from .run import load_run

    run = load_run(args.rundir)
    if args.baked is not None:
        run = run.baked(args.baked)
    edit = None if args.palette is None else read_palette_json(args.palette, k=len(run.palette))
    dataset = run.dataset()
    scores = evaluate(run, dataset, edit)
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


if __name__ == "__main__":
    sys.exit(main())
