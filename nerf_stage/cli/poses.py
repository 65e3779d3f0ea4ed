"""``nerf-stage poses``: camera poses for a folder of photos (``sfm.estimate_poses``)."""

from __future__ import annotations

from pathlib import Path

from palette_core.stack import DEFAULT_STACK


def add(commands) -> None:
    from ..data.photos import MATCHERS
    from ..data.sfm import CAMERA_MODELS, MAPPERS

    poses = commands.add_parser(
        "poses", help="camera poses for a folder of photos (structure from motion, pycolmap)",
        description="Estimate the cameras of a folder of photos with COLMAP's structure from "
                    "motion (pycolmap, on the CPU), or convert the COLMAP model a folder "
                    "already holds (sparse/0, text or binary, with its photos in images/), "
                    "or keep the poses of a capture that has them (transforms.json, or a "
                    "Blender scene's files) and triangulate its points from them. Writes a "
                    "capture folder: images/, transforms.json (nerfstudio layout) and the "
                    "sparse points that splat runs start at, undistorted where the camera "
                    "distorts.")
    poses.add_argument("source", metavar="PHOTOS",
                       help="folder of photos, of a COLMAP model, or a capture with poses")
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
    poses.set_defaults(run=run)


def run(args) -> int:
    from ..data.sfm import estimate_poses

    report = estimate_poses(args.source, args.output, args.camera_model, args.matcher,
                            args.mapper, args.force)
    total = len(report.registered) + len(report.missing)
    print((f"kept the poses of {total} photos, triangulated" if report.posed else
           f"registered {len(report.registered)} of {total} photos:")
          + f" {report.points} points, "
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
          f"nerf-stage train {args.output}")
    return 0


