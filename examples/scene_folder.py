"""Build a capture folder to try the project card's three commands on, in about a minute.

    python examples/scene_folder.py my_scene [--resolution 64] [--views 40]
    cd my_scene
    palette-decompose images/ -k 5
    palette-harmonize --template double-split
    nerf-stage train

The folder is the nerfstudio layout (``images/frame_00001.png``, ...,
``transforms.json``), path traced from the built-in ``still-life`` scene by
``nerf-stage simulate --layout nerfstudio``.
"""

from __future__ import annotations

import argparse
import sys

from nerf_stage.cli import main as nerf_stage


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", help="capture folder to create")
    parser.add_argument("--resolution", type=int, default=64, help="pixels (default 64)")
    parser.add_argument("--views", type=int, default=40, help="views (default 40)")
    parser.add_argument("--force", action="store_true", help="replace a non-empty folder")
    args = parser.parse_args()
    code = nerf_stage(["simulate", "still-life", args.folder, "--layout", "nerfstudio",
                       "--resolution", str(args.resolution), "--views", str(args.views), "0", "0",
                       *(["--force"] if args.force else [])])
    if code == 0:
        print(f"\nnow: cd {args.folder} && palette-decompose images/ -k 5 && "
              "palette-harmonize --template double-split && nerf-stage train")
    return code


if __name__ == "__main__":
    sys.exit(main())
