"""``nerf-stage bake`` and ``export``: a run as splats (``splats.bake_to``), splats as a
PLY or an SPZ (``splats.export_splats``)."""

from __future__ import annotations

from palette_core.palette_file import read_palette_json


def add(commands) -> None:
    from ..splats import MAX_SPLATS, REFINE_STEPS, SPLAT_CACHE

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
    bake.set_defaults(run=run_bake)
    export = commands.add_parser(
        "export", help="write recoloured splats as a 3D Gaussian splatting PLY or SPZ",
        description="Write the splats of a splat run or a bake (nerf-stage bake), recoloured "
                    "with a palette, as a binary PLY in the layout 3D Gaussian splatting "
                    "viewers read, or as Niantic's compressed SPZ (the spz extra), as the "
                    "output's suffix says.")
    export.add_argument("bake", metavar="FILE.splat.npz|RUNDIR",
                        help=f"a bake, or a run folder: its {SPLAT_CACHE}, baked first when it "
                             "is missing or older than the run")
    export.add_argument("--palette", metavar="JSON", default=None,
                        help="palette file of the run's K colours (default: the run's own)")
    export.add_argument("-o", "--output", required=True, metavar="FILE.ply|FILE.spz")
    export.add_argument("--force", action="store_true", help="overwrite the output")
    export.set_defaults(run=run_export)


def run_bake(args) -> int:
    from ..splats import bake_to

    splats, output = bake_to(args.rundir, args.output, args.max_splats, args.refine_steps,
                             args.force)
    print(f"wrote {len(splats)} splats to {output} ({output.stat().st_size / 2**20:.1f} MB); "
          f"next: nerf-stage export {args.output or args.rundir} --palette P.json -o scene.ply")
    return 0


def run_export(args) -> int:
    from ..splats import export_splats, splats_of

    splats = splats_of(args.bake)
    palette = (None if args.palette is None
               else read_palette_json(args.palette, k=len(splats.palette)))
    output = export_splats(splats, args.output, palette, force=args.force)
    print(f"wrote {len(splats)} splats to {output}")
    return 0
