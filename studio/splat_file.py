"""Splat-file mode: a splat file of another tool (decomposed as it opens) or its splat stack,
drawn by the browser as splats and recoloured by the palette's change (``splat_files``;
docs/splat_files.md). There is no network: the splats are the scene."""

from __future__ import annotations

import math
import os
import sys
from pathlib import Path

import numpy as np

from nerf_stage.data.cameras import Intrinsics, look_at
from nerf_stage.edit.regions import Region
from nerf_stage.splats import Splats
from palette_core.basis import Basis
from palette_core.errors import InputError
from splat_files import read_splat_file, write_splat_file
from splat_files.formats import format_of
from splat_files.stack import SplatStack, decompose_splats, read_splat_stack

FOV_Y = math.radians(50)
#: The PLY's frame is y down: its scenes stand along -y.
UP = np.array([0.0, -1.0, 0.0])


class SplatFileTarget:
    """A splat stack to recolour in the studio, with the interface of ``SceneTarget`` that
    the scene view uses (``run`` None: the browser's splats are all there is).

    Parameters
    ----------
    stack : SplatStack
    path : Path
        The file it came from (default exports go beside it).
    """

    mode = "splat file"
    run = None
    rows = 480  # of a turntable's or still's frame: none here, but the view asks

    def __init__(self, stack: SplatStack, path: Path):
        self.stack, self.path = stack, path
        f = stack.fields
        base = stack.weights @ stack.palette.astype(np.float32)
        quats = f.quats / np.linalg.norm(f.quats, axis=1, keepdims=True)
        self.splats = Splats(f.means, np.exp(f.scales), quats,
                             1 / (1 + np.exp(-f.opacities)), stack.weights, stack.palette,
                             Basis.ADDITIVE, 1, np.zeros(3), {"file": path.name},
                             offset=(stack.colours() - base).astype(np.float32))
        self.up = UP
        self.bounds = np.percentile(f.means, [1, 99], axis=0)
        self.centre = self.bounds.mean(0)

    @classmethod
    def open(cls, path: str | os.PathLike, k: int = 6) -> SplatFileTarget:
        """A splat stack, or a splat file decomposed into ``k`` colours as it opens."""
        path = Path(path)
        if format_of(path) is None:
            return cls(read_splat_stack(path), path)
        print(f"decomposing {path} into {k} colours", file=sys.stderr)
        return cls(decompose_splats(read_splat_file(path), k), path)

    @property
    def palette(self) -> np.ndarray:
        return self.stack.palette

    @property
    def fov_y(self) -> float:
        return FOV_Y

    def shares(self) -> np.ndarray:
        return self.stack.shares()

    def home_pose(self) -> np.ndarray:
        """(4, 4) a camera 20 degrees above the splats' middle, framing their central 98 %."""
        reach = 0.5 * np.linalg.norm(np.ptp(self.bounds, 0))
        offset = np.array([0.0, -math.sin(math.radians(20)), math.cos(math.radians(20))])
        return look_at(self.centre + 1.2 * reach / math.sin(FOV_Y / 2) * offset, self.centre,
                       up=tuple(UP))

    def intrinsics(self, aspect: float, height: int) -> Intrinsics:
        width = max(1, round(height * aspect))
        focal = 0.5 * height / math.tan(FOV_Y / 2)
        return Intrinsics(width, height, focal, focal, width / 2, height / 2)

    def default_palette(self) -> Path:
        return self.path.with_name(self.path.name.split(".")[0] + ".edited_palette.json")

    def default_export(self) -> Path:
        return self.path.with_name(self.path.name.split(".")[0] + ".edited.ply")

    def export(self, path: str | os.PathLike, palette: np.ndarray, pose=None,
               intrinsics=None, views: int = 0, force: bool = False,
               regions: list[Region] = ()) -> list[Path]:
        """The splats recoloured with ``palette`` (inside ``regions`` only, when given) into
        the splat file ``path`` (``splat_files.write_splat_file``)."""
        inside = (np.any([region.contains(self.stack.fields.means) for region in regions], 0)
                  if regions else None)
        if Path(path).suffix.lower() == ".gif":
            raise InputError("a splat file has no network for a turntable: export the splats "
                             "(.ply, .compressed.ply, .spz or .splat)")
        return [write_splat_file(self.stack.recoloured(palette, inside=inside), path, force)]
