"""``nerf-stage``: simulate scenes (and, with issue 6, train / render / eval NeRFs)."""

from __future__ import annotations

import sys
from pathlib import Path

from palette_core.cli import ArgumentParser, run_cli

from .simulation import (
    BUILTIN_SCENES,
    check_outdir,
    load_scene,
    simulate,
    with_overrides,
    write_dataset,
)

PROG = "nerf-stage"


def build_parser() -> ArgumentParser:
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
    sim.add_argument("--seed", type=int, default=None, help="random seed (default: the scene's)")
    sim.add_argument("--force", action="store_true", help="replace a non-empty OUTDIR")
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_cli(PROG, lambda: _run(build_parser().parse_args(argv)))


def _run(args) -> int:
    scene = with_overrides(load_scene(args.scene), order=args.order, spp=args.spp,
                           resolution=args.resolution, views=args.views, seed=args.seed)
    check_outdir(args.outdir, args.force)
    sim = simulate(scene)
    spec = args.scene if args.scene in BUILTIN_SCENES else str(Path(args.scene).resolve())
    written = write_dataset(sim, scene, args.outdir, spec, force=args.force)
    cam, render = scene.camera, scene.render
    print(f"{scene.name}: {len(sim.names)} views of {cam.width}x{cam.height}, {render.spp} spp, "
          f"{render.light} light" + (f", order {sim.order}" if sim.weights is not None else "")
          + f", traced in {sim.seconds:.1f} s")
    if sim.weights is not None:
        print(f"palette ({len(sim.palette)} editable materials, {sim.weights.shape[-1]} transport "
              f"terms): see {args.outdir}/materials.json")
    print(f"wrote {len(written)} files to {args.outdir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
