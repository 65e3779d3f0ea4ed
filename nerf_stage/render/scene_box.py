"""The scene box: the axis-aligned box around what the cameras see, in which every field
lives, and rays normalised into it. In an unbounded scene the box is a cube and what lies
beyond it is contracted into a shell around it (``contraction``).

References
----------
A. Laurentini. The visual hull concept for silhouette-based image understanding. IEEE
PAMI 16(2), 1994 (carving space that a transparent pixel shows empty).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import maximum_filter

from palette_core.errors import InputError

from ..data.cameras import Intrinsics, camera_rays, project
from . import contraction
from .ndc import NDCFrame, frame_from_dict, reference_frame

CARVE_ALPHA = 0.01  # a pixel below this alpha (after dilation) shows empty space
OPAQUE_ALPHA = 1 - 0.5 / 255  # images whose pixels are all this opaque show no background
#: An unbounded scene's cube grows until every camera lies within this many half sizes of its
#: centre (infinity norm): a ray from a camera far outside it would march hundreds of steps
#: through the shell before it reached the cube.
CAMERA_REACH = 2.0


@dataclass
class SceneBox:
    """Axis-aligned box around the scene; positions are normalised as (x - centre) / scale.

    Attributes
    ----------
    centre : (3,) float
    half : (3,) float
        World half sizes.
    unbounded : bool
        The scene goes on beyond the box (a cube then), contracted into a shell around it.
    sky : bool
        Rays of an unbounded or NDC scene end in an opaque sky at infinity (every training
        pixel is opaque: ``rendering.march_rays``); else what they leave shows the background.
    ndc : NDCFrame or None
        A forward-facing scene in NDC space (``ndc``): fields and the occupancy grid cover
        the reference camera's frustum mapped onto [-1, 1]^3; the box only normalises.
    """

    centre: np.ndarray
    half: np.ndarray
    unbounded: bool = False
    sky: bool = False
    ndc: NDCFrame | None = None

    @property
    def scale(self) -> float:
        return float(np.max(self.half))

    @property
    def extent(self) -> np.ndarray:
        """(3,) half sizes of the normalised box (the largest is 1)."""
        return self.half / self.scale

    @property
    def field_extent(self) -> np.ndarray:
        """(3,) half sizes of the space fields and the occupancy grid cover: the normalised
        box, the contracted space around it, or the NDC cube."""
        if self.ndc is not None:
            return np.ones(3)
        return np.full(3, contraction.EXTENT) if self.unbounded else self.extent

    def to_dict(self) -> dict:
        return {"centre": self.centre.tolist(), "half": self.half.tolist(),
                "unbounded": self.unbounded, "sky": self.sky,
                "ndc": None if self.ndc is None else self.ndc.to_dict()}


def box_from_dict(data, source: str) -> SceneBox:
    """The box of ``SceneBox.to_dict`` from a checkpoint named ``source``, checked.

    Raises
    ------
    InputError
        If it is not a finite box with positive extent.
    """
    try:
        box = SceneBox(np.array(data["centre"], np.float64), np.array(data["half"], np.float64),
                       data.get("unbounded", False) is True, data.get("sky", False) is True)
    except (KeyError, TypeError, ValueError, AttributeError):
        box = None
    if (box is None or box.centre.shape != (3,) or box.half.shape != (3,)
            or not np.isfinite(box.centre).all()
            or not (np.isfinite(box.half) & (box.half > 0)).all()):
        raise InputError(f"{source}: the scene box must be finite with positive extent")
    if data.get("ndc") is not None:
        box.ndc = frame_from_dict(data["ndc"], source)
    return box


def scene_box(poses: np.ndarray, intrinsics: list[Intrinsics], alpha: np.ndarray,
              space: str = "auto", resolution: int = 64, depth: float | None = None,
              nearest: float | None = None) -> SceneBox:
    """A box around what the cameras (``poses``, one ``intrinsics`` each) see.

    Starts from the cube around the point nearest to all optical axes, with half
    size 0.75 x the nearest camera's distance. Cameras that all face one way (a
    forward-facing capture) have axes that meet nowhere in front of them: when that point
    is not in front of them (``in_front``), the cube is centred ``depth`` (where the scene
    is: twice an LLFF capture's near bound, or its points' median depth; by default the
    cameras' spread) along their mean axis from their mean position. ``space``
    ``unbounded`` keeps that cube, grown where needed to bring every camera within
    ``CAMERA_REACH`` half sizes (cameras whose axes do not meet, as on a walk down a street,
    can put that point beside one of them), and contracts the rest of space around it;
    ``box`` ends the scene there and, when the images have transparent pixels, shrinks the
    box to the visual hull carved from them; ``auto`` is ``unbounded`` when every pixel is
    opaque (no view shows where the scene ends), else ``box`` (training may still probe
    both: ``trainer.choose_scene_box``); ``ndc`` keeps the cube to normalise positions and
    maps the cameras' frustum, from a near plane at ``ndc.NEAR_SHARE`` of the ``nearest``
    depth the capture gives, onto the fields' cube (``ndc``).

    Raises
    ------
    InputError
        If the cameras all stand at one point (a panorama: no box around a scene), or
        ``ndc`` without a ``nearest`` depth.
    """
    axes = -poses[:, :3, 2]
    eyes = poses[:, :3, 3]
    projector = np.eye(3) - axes[:, :, None] * axes[:, None, :]  # (N, 3, 3)
    centre = np.linalg.lstsq(projector.sum(0), np.einsum("nij,nj->i", projector, eyes),
                             rcond=None)[0]
    if not in_front(centre, eyes, axes):
        mean_axis = axes.mean(0) / max(np.linalg.norm(axes.mean(0)), 1e-12)
        spread = np.linalg.norm(eyes - eyes.mean(0), axis=1).max()
        centre = eyes.mean(0) + (depth or spread) * mean_axis
    half = 0.75 * np.linalg.norm(eyes - centre, axis=1).min()
    opaque = bool(alpha.min() >= OPAQUE_ALPHA)
    unbounded = space == "unbounded" or (space == "auto" and opaque)
    if unbounded:
        half = max(half, np.abs(eyes - centre).max() / CAMERA_REACH)
    if not half > 0:
        raise InputError("the training cameras all stand at one point: a NeRF needs views "
                         "from several places")
    box = SceneBox(centre, np.full(3, half), unbounded, unbounded and opaque)
    if space == "ndc":
        box.ndc, box.sky = reference_frame(poses, intrinsics, nearest, centre, half), opaque
        return box
    if unbounded or alpha.min() >= CARVE_ALPHA:
        return box
    cells = np.argwhere(visual_hull(box, np.full(3, resolution), poses, intrinsics, alpha))
    if len(cells) == 0:
        return box
    cell = 2 * half / resolution
    lo = centre - half + (cells.min(0) - 1) * cell
    hi = centre - half + (cells.max(0) + 2) * cell
    lo, hi = np.maximum(lo, centre - half), np.minimum(hi, centre + half)
    return SceneBox((lo + hi) / 2, (hi - lo) / 2)


def in_front(point: np.ndarray, eyes: np.ndarray, axes: np.ndarray) -> bool:
    """Whether ``point`` lies in front of most cameras (``eyes``, unit ``axes`` (N, 3)): its
    median depth along their axes is positive."""
    return bool(np.median(np.einsum("ni,ni->n", point - eyes, axes)) > 0)


def visual_hull(box: SceneBox, resolution: np.ndarray, poses: np.ndarray,
                intrinsics: list[Intrinsics], alpha: np.ndarray) -> np.ndarray:
    """(X, Y, Z) bool: cells of ``box`` that no view shows as transparent.

    A cell is carved when its centre projects inside a view onto a pixel whose
    alpha, dilated by the cell's footprint in that view, is below ``CARVE_ALPHA``.
    """
    axes = [np.linspace(-1, 1, n, endpoint=False) + 1 / n for n in resolution]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    points = box.centre + grid * box.half
    keep = np.ones(len(points), bool)
    radius = 0.5 * float(np.linalg.norm(2 * box.half / resolution))  # of a cell's bounding ball
    for pose, camera, mask in zip(poses, intrinsics, alpha):
        u, v, depth = project(points, pose, camera)
        ahead = depth > radius
        safe = np.where(ahead, depth, 1.0)
        inside = ahead & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        ui = np.clip(u, 0, camera.width - 1).astype(np.int64)
        vi = np.clip(v, 0, camera.height - 1).astype(np.int64)
        footprint = np.ceil(camera.fx * radius / safe).astype(np.int64)  # pixels
        carved = np.zeros(len(points), bool)
        for pixels in np.unique(footprint[inside]):
            dilated = maximum_filter(mask, size=2 * int(pixels) + 1)
            at = inside & (footprint == pixels)
            carved[at] = dilated[vi[at], ui[at]] < CARVE_ALPHA
        keep &= ~carved
    return keep.reshape(tuple(resolution))


def normalised_rays(pose, intrinsics: Intrinsics, box: SceneBox, device, supersampling: int = 1):
    """(H W, n^2, 3) origins in the normalised box and unit directions of one camera's n^2
    rays a pixel (``cameras.camera_rays``), float32."""
    origins, directions = camera_rays(pose, intrinsics, supersampling)
    origins = (origins - box.centre) / box.scale
    shape = (-1, supersampling ** 2, 3)
    return (torch.as_tensor(origins.reshape(shape), dtype=torch.float32, device=device),
            torch.as_tensor(directions.reshape(shape), dtype=torch.float32, device=device))
