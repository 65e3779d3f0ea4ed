"""``nerf-stage simulate``: path trace a scene into a dataset (``simulation.simulate_to``)."""

from __future__ import annotations

from ..simulation import BUILTIN_SCENES, LAYOUTS, simulate_to


def add(commands) -> None:
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
    sim.set_defaults(run=run)


def run(args) -> int:
    scene, sim, written = simulate_to(
        args.scene, args.outdir, args.layout, args.force, order=args.order, spp=args.spp,
        resolution=args.resolution, views=args.views, seed=args.seed, off_ring=args.off_ring)
    cam, render = scene.camera, scene.render
    print(f"{scene.name}: {len(sim.names)} views of {cam.width}x{cam.height}, {render.spp} spp, "
          f"{render.light} light" + (f", order {sim.order}" if sim.weights is not None else "")
          + f", traced in {sim.seconds:.1f} s")
    if sim.weights is not None and args.layout == "blender":
        print(f"palette ({len(sim.palette)} editable materials, {sim.weights.shape[-1]} transport "
              f"terms): see {args.outdir}/materials.json")
    print(f"wrote {len(written)} files to {args.outdir}")
    return 0
