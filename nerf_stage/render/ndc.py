"""Forward-facing scenes in normalised device coordinates (NDC): the frustum of one reference
camera, from its near plane to infinity, mapped onto the cube [-1, 1]^3.

A point c in the reference camera's frame (OpenGL axes: it looks down -z) maps to

    ndc(c) = (-sx c_x / c_z, -sy c_y / c_z, 1 + 2 near / c_z),   sx = 2 fx / W, sy = 2 fy / H,

a projective map, so rays stay straight lines and the march, the occupancy grid and the
fields work in the cube as in a bounded box. A ray starts where it crosses the near plane
(z = -1) and reaches z = 1 at infinity; steps of equal length in the cube are steps of equal
disparity along it (NeRF, appendix C). The reference camera is the training cameras' mean
(LLFF's ``poses_avg``), the near plane ``NEAR_SHARE`` of the nearest bound (LLFF's
``bd_factor``), its field of view as wide as all the training views'. As NeRF's last sample
takes an infinite step, a ray of a capture whose pixels are all opaque ends in an opaque sky
where it leaves the cube (``march._sky_samples``).

References
----------
B. Mildenhall et al. NeRF. ECCV 2020, appendix C (``ndc_rays``).
B. Mildenhall et al. Local light field fusion. SIGGRAPH 2019 (``poses_bounds.npy``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from palette_core.errors import InputError

from ..data.cameras import Intrinsics

#: The near plane lies at this share of the nearest depth the capture gives.
NEAR_SHARE = 0.75
#: Cameras face one way (``forward_facing``) when every optical axis lies within this many
#: degrees of their mean.
FORWARD_SPREAD = 30.0
FAR_Z = 1 - 1e-6  # points are taken back to the world no further than this NDC depth


@dataclass
class NDCFrame:
    """The reference camera of NDC space, in the scene box's normalised coordinates.

    Attributes
    ----------
    rotation : (3, 3) float64
        Camera-to-box rotation (columns: right, up, back).
    eye : (3,) float64
    near : float
        Distance of the near plane in front of ``eye``.
    sx, sy : float
        2 fx / W and 2 fy / H of the reference camera.
    """

    rotation: np.ndarray
    eye: np.ndarray
    near: float
    sx: float
    sy: float

    def _tensors(self, like: torch.Tensor):
        return (torch.as_tensor(self.rotation, dtype=like.dtype, device=like.device),
                torch.as_tensor(self.eye, dtype=like.dtype, device=like.device))

    def rays(self, origins: torch.Tensor, directions: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor]:
        """(R, 3) rays in the normalised box -> (R, 3) origins on the near plane and unit
        directions in NDC; a ray that does not go forward (away from the reference camera's
        near plane) gets the origin (0, 0, 2), outside the cube, which it then misses."""
        rotation, eye = self._tensors(origins)
        o, d = (origins - eye) @ rotation, directions @ rotation  # camera frame
        forward = d[:, 2] < -1e-9
        dz = torch.where(forward, d[:, 2], torch.full_like(d[:, 2], -1.0))
        o = o + ((-self.near - o[:, 2]) / dz)[:, None] * d  # on the near plane
        scale = o.new_tensor([self.sx, self.sy])
        start = torch.cat([-scale * o[:, :2] / o[:, 2:], -torch.ones_like(o[:, 2:])], 1)
        end = torch.cat([-scale * d[:, :2] / dz[:, None], torch.ones_like(o[:, 2:])], 1)
        towards = torch.nn.functional.normalize(end - start, dim=1)
        missed = start.new_tensor([0.0, 0.0, 2.0])
        return torch.where(forward[:, None], start, missed), towards

    def from_box(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) points in the normalised box, in front of the reference camera -> (..., 3)
        NDC points (``ndc``)."""
        rotation, eye = self._tensors(points)
        c = (points - eye) @ rotation
        z = c[..., 2].clamp(max=-1e-12)
        return torch.stack([-self.sx * c[..., 0] / z, -self.sy * c[..., 1] / z,
                            1 + 2 * self.near / z], -1)

    def to_box(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) NDC points -> (..., 3) the same points in the normalised box."""
        rotation, eye = self._tensors(points)
        z = 2 * self.near / (points[..., 2].clamp(max=FAR_Z) - 1)
        camera = torch.stack([-points[..., 0] * z / self.sx, -points[..., 1] * z / self.sy, z],
                             -1)
        return camera @ rotation.T + eye

    def to_dict(self) -> dict:
        return {"rotation": self.rotation.tolist(), "eye": self.eye.tolist(),
                "near": float(self.near), "sx": float(self.sx), "sy": float(self.sy)}


def frame_from_dict(data, source: str) -> NDCFrame:
    """The frame of ``NDCFrame.to_dict`` from a checkpoint named ``source``, checked.

    Raises
    ------
    InputError
        Unless it is a finite rotation, eye and positive near plane and scales.
    """
    try:
        frame = NDCFrame(np.array(data["rotation"], np.float64), np.array(data["eye"], np.float64),
                         float(data["near"]), float(data["sx"]), float(data["sy"]))
    except (KeyError, TypeError, ValueError):
        frame = None
    if (frame is None or frame.rotation.shape != (3, 3) or frame.eye.shape != (3,)
            or not np.isfinite(frame.rotation).all() or not np.isfinite(frame.eye).all()
            or not np.allclose(frame.rotation @ frame.rotation.T, np.eye(3), atol=1e-6)
            or not all(np.isfinite(v) and v > 0 for v in (frame.near, frame.sx, frame.sy))):
        raise InputError(f"{source}: the NDC frame must be a rotation, an eye and positive "
                         "near plane and scales")
    return frame


def forward_facing(poses: np.ndarray) -> bool:
    """Whether cameras ``poses`` (N, 4, 4) all face one way, as a forward-facing capture's
    do (LLFF's; not those around an object): every optical axis within ``FORWARD_SPREAD``
    degrees of their mean."""
    axes = -poses[:, :3, 2]
    mean = axes.mean(0)
    length = np.linalg.norm(mean)
    return bool(length > 1e-12
                and (axes @ (mean / length)).min() >= np.cos(np.radians(FORWARD_SPREAD)))


def reference_frame(poses: np.ndarray, cameras: list[Intrinsics], nearest: float | None,
                    centre: np.ndarray, scale: float) -> NDCFrame:
    """The NDC frame of training cameras ``poses`` (N, 4, 4), one of ``cameras`` each: their
    mean pose (mean eye, mean optical axis, mean up made orthogonal to it) with the near
    plane at ``NEAR_SHARE`` of the ``nearest`` depth the capture gives, all in the box
    normalised by ``centre`` and ``scale``, its field of view widened until it holds every
    training ray from the near plane to infinity (a grid ends at the cube's sides, where
    NeRF's network does not).

    Raises
    ------
    InputError
        Without a nearest depth (NDC needs LLFF's bounds or sparse points).
    """
    if nearest is None or not nearest > 0:
        raise InputError("--space ndc needs the capture's depth bounds (LLFF's "
                         "poses_bounds.npy) or sparse points, to place its near plane")
    back = poses[:, :3, 2].mean(0)
    back /= np.linalg.norm(back)
    right = np.cross(poses[:, :3, 1].mean(0), back)
    right /= np.linalg.norm(right)
    rotation = np.stack([right, np.cross(back, right), back], 1)
    eye = (poses[:, :3, 3].mean(0) - centre) / scale
    frame = NDCFrame(rotation, eye, NEAR_SHARE * nearest / scale, 1.0, 1.0)
    origins, directions = zip(*(_corner_rays(pose, camera) for pose, camera in
                                zip(poses, cameras)))
    start, towards = frame.rays(torch.as_tensor((np.concatenate(origins) - centre) / scale),
                                torch.as_tensor(np.concatenate(directions)))
    end = start + towards * (2 / towards[:, 2:].clamp(min=1e-12))  # where z reaches 1
    reach = torch.cat([start, end])[:, :2].abs().amax(0).numpy()
    return NDCFrame(rotation, eye, frame.near, 1 / reach[0], 1 / reach[1])


def _corner_rays(pose: np.ndarray, camera: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(4, 3) world origins and unit directions of the rays through a camera's corners."""
    x = (np.array([0, camera.width, 0, camera.width]) - camera.cx) / camera.fx
    y = -(np.array([0, 0, camera.height, camera.height]) - camera.cy) / camera.fy
    directions = np.stack([x, y, -np.ones(4)], 1) @ pose[:3, :3].T
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return np.broadcast_to(pose[:3, 3], (4, 3)), directions
