"""Scene mode: a trained weight NeRF, drawn by the browser as splats or rendered by the
network from the browser's camera.

The run is baked into splats on first open and the bake kept in the run folder
(``nerf_stage.splats.cached_bake``); the browser draws them, and a palette change sends
their new colours. The network runs once per camera view and resolution; the weights are
cached with the samples behind each pixel, and a palette change, or a region moved
(``nerf_stage.edit.regions``), recolours them (``nerf_stage.edit.editing.WeightRender``) without
running it again.
"""

from __future__ import annotations

import math
import os
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from harmonize import palette_shares
from nerf_stage.data.cameras import Intrinsics, look_at, turntable_poses
from nerf_stage.edit.editing import WeightRender, render_weights, write_gif
from nerf_stage.edit.regions import Region
from nerf_stage.fields import RGB
from nerf_stage.splats import WRITERS, Splats, cached_bake, export_splats
from nerf_stage.train.loading import load_run
from nerf_stage.train.run import RunBase
from palette_core.errors import InputError
from palette_core.outputs import atomic_outputs, check_writable

from .guard import log

CACHED_VIEWS = 32


def recoloured(render: WeightRender, palette: np.ndarray, regions: list[Region]) -> np.ndarray:
    """(N, H, W, 3) ``render`` recoloured with ``palette``, inside ``regions`` only (the run's
    own palette outside) when there are any."""
    if not regions:
        return render.recolor(palette)
    return render.with_regions(regions).recolor(render.palette, inside=palette)
SHARE_VIEWS, SHARE_SIZE = 8, 32  # the low-resolution turntable that harmonisation weighs
MAX_TURNTABLE = 360


class SceneTarget:
    """A ``nerf-stage train`` run folder to recolour in the studio.

    Parameters
    ----------
    run : RunBase
    path : Path
        The run folder (default exports go into it).

    Attributes
    ----------
    splats : nerf_stage.splats.Splats or None
        The bake the browser draws (None: the network only).
    home : (4, 4) float64 or None
        The first training camera, where a new tab starts.
    up : (3,) float64
        The training cameras' mean up (unit; +y when they have none): the axis the browser's
        camera orbits about.
    bounds : (2, 3) float64
        World corners of what the run found occupied (``Run.bounds``).
    centre : (3,) float64
        Their middle: where the camera looks and turntables turn.
    """

    mode = "scene"

    def __init__(self, run: RunBase, path: Path, splats: Splats | None = None,
                 home: np.ndarray | None = None, up: np.ndarray | None = None):
        self.run = run
        self.path = path
        self.splats, self.home = splats, home
        self.up = np.array([0.0, 1.0, 0.0]) if up is None else up
        self.bounds = run.bounds()
        self.centre = self.bounds.mean(0)
        self._views: OrderedDict[tuple, WeightRender] = OrderedDict()
        self._lock = threading.Lock()  # one render at a time, whichever tab asks

    @classmethod
    def open(cls, path: str | os.PathLike, bake: bool = True, **bake_options) -> SceneTarget:
        """The run in folder ``path``, baked (or its kept bake; ``bake_options`` go to
        ``cached_bake``) unless not ``bake``. A run that does not bake (still fog) opens
        with the network only, and says why on stderr."""
        run = load_run(path)
        if run.kind == RGB:
            raise InputError(f"{path} was trained on RGB only (strategy 'rgb'): it has no "
                             "weights to recolour")
        dataset = run.dataset()
        train = dataset.indices("train")
        home = dataset.poses[train[0]]
        up = dataset.poses[train, :3, 1].sum(0)
        up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-6 else None
        splats = None
        if bake:
            try:
                splats = cached_bake(run, path, dataset=dataset, **bake_options)
            except InputError as exc:
                log(f"no splats, the network draws every view: {exc}")
        return cls(run, Path(path), splats, home, up)

    @property
    def palette(self) -> np.ndarray:
        return self.run.palette

    @property
    def rows(self) -> int:
        """Rows of a full-quality view: the training camera's."""
        return self.run.intrinsics.height

    def default_palette(self) -> Path:
        return self.path / "edited_palette.json"

    @property
    def fov_y(self) -> float:
        """Vertical field of view of the training camera, radians."""
        return 2 * math.atan(0.5 * self.run.intrinsics.height / self.run.intrinsics.fy)

    def home_pose(self) -> np.ndarray:
        """(4, 4) the first training camera, or else a camera in front of the scene (+z), 20
        degrees up, framing all that the run found occupied."""
        if self.home is not None:
            return self.home
        distance = 0.6 * np.linalg.norm(np.ptp(self.bounds, 0)) / math.sin(0.5 * self.fov_y)
        up = math.radians(20)
        return look_at(self.centre + distance * np.array([0, math.sin(up), math.cos(up)]),
                       self.centre)

    def intrinsics(self, aspect: float, height: int) -> Intrinsics:
        """A camera of the training camera's vertical field of view, ``height`` rows and
        ``aspect`` (width / height)."""
        width = max(1, round(height * aspect))
        focal = 0.5 * height / math.tan(0.5 * self.fov_y)
        return Intrinsics(width, height, focal, focal, width / 2, height / 2)

    def render(self, pose: np.ndarray, intrinsics: Intrinsics) -> WeightRender:
        """The weights of one view and the samples behind its pixels (cached by pose and
        camera)."""
        key = (np.round(pose, 6).tobytes(), intrinsics.width, intrinsics.height)
        with self._lock:
            if key not in self._views:
                self._views[key] = render_weights(self.run, ["view"], pose[None], {}, False,
                                                  intrinsics, samples=True)
                if len(self._views) > CACHED_VIEWS:
                    self._views.popitem(last=False)
            self._views.move_to_end(key)
            return self._views[key]

    def shares(self) -> np.ndarray:
        """(K,) each colour's share of the weights of a low-resolution turntable."""
        poses = turntable_poses(self.home_pose(), self.centre, SHARE_VIEWS)
        render = render_weights(self.run, [f"turn_{i}" for i in range(SHARE_VIEWS)], poses, {},
                                False, self.intrinsics(1.0, SHARE_SIZE))
        return palette_shares(render.as_stack())

    def default_export(self) -> Path:
        return self.path / "turntable.gif"

    def export(self, path: str | os.PathLike, palette: np.ndarray, pose: np.ndarray,
               intrinsics: Intrinsics, views: int = 36, force: bool = False,
               regions: list[Region] = ()) -> list[Path]:
        """A turntable GIF of ``views`` frames from ``pose``, or the splats as a PLY or an
        SPZ (``nerf_stage.splats.export_splats``), as the suffix of ``path`` says, recoloured
        with ``palette`` (inside ``regions`` only, when given)."""
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix != ".gif" and suffix not in WRITERS:
            raise InputError(f"export a turntable as .gif or the splats as "
                             f"{' or '.join(WRITERS)}, got {path}")
        if suffix in WRITERS and self.splats is None:
            raise InputError("this run has no splats to export (the studio opened it without "
                             "them): export a turntable (.gif)")
        if not 1 <= views <= MAX_TURNTABLE:
            raise InputError(f"a turntable has 1 to {MAX_TURNTABLE} views, got {views}")
        if suffix in WRITERS:
            return [export_splats(self.splats, path, palette, regions, force)]
        check_writable([path], force)
        poses = turntable_poses(pose, self.centre, views)
        frames = np.concatenate([recoloured(self.render(p, intrinsics), palette, regions)
                                 for p in poses])
        with atomic_outputs(force) as stage:
            write_gif(stage(path), frames)
        return [path]
