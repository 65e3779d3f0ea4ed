"""Splats projected into a view: each splat's screen centre, the inverse of its projected
covariance (EWA splatting's Jacobian, Mip-Splatting's 2D filter), its peak opacity, and
the box of pixels its ellipse at alpha 1/255 may touch; what both ways of drawing them
(``tiles`` on a CPU, ``pairs`` in PyTorch) start from.

References
----------
B. Kerbl et al. 3D Gaussian splatting for real-time radiance field rendering. SIGGRAPH
2023 (projection of the covariances, the low-pass filter, the Jacobian's clamp).
M. Zwicker et al. EWA splatting. IEEE TVCG 8(3), 2002.
Z. Yu et al. Mip-Splatting: alias-free 3D Gaussian splatting. CVPR 2024 (the 2D filter).
"""

from __future__ import annotations

import torch

from ..data.cameras import Intrinsics

#: Pixels^2 added to every projected covariance: Mip-Splatting's 2D filter. (3D Gaussian
#: splatting's 0.3, which viser adds at the screen's resolution, let splats fitted at the
#: training views' resolution lean on that blur to cover surfaces: holes where a browser
#: draws them finer; docs/splats.md.)
LOW_PASS = 0.1
#: Splats nearer to the camera than this (in the splats' units; the scene box's half size
#: for a splat run) are not drawn: their projection's Jacobian grows as 1 / depth^2.
NEAR = 0.01
FOV_CLAMP = 1.3  # of the view's half angle, where the Jacobian is taken at most


def project(centres, covariances, opacities, pose, camera: Intrinsics, reach: int | None,
             info: dict | None, window: tuple[int, int, int, int]):
    """Each splat in front of the camera projected (``table`` (F, 6): centre u, v, inverse
    covariance a, b, c, peak opacity; with gradients), its ``box`` (F, 5): x0, x1, y0, y1
    in the ``window`` and the Mahalanobis ``level`` of alpha 1/255, the splats' ``index``
    (F,) and the rows that show, front to back; None when none shows."""
    left, top, width, height = window
    pose = pose.to(centres.dtype)
    rotation, origin = pose[:3, :3], pose[:3, 3]
    local = (centres - origin) @ rotation  # camera axes: x right, y up, looking down -z
    depth = -local[:, 2]
    index = torch.nonzero(depth > NEAR)[:, 0]
    local, depth = local.index_select(0, index), depth.index_select(0, index)
    covariances = covariances.index_select(0, index)
    fx, fy = camera.fx, camera.fy
    u = camera.cx + fx * local[:, 0] / depth
    v = camera.cy - fy * local[:, 1] / depth
    if info is not None and u.requires_grad:
        means2d = torch.stack([u, v], 1)
        means2d.retain_grad()
        u, v = means2d.unbind(1)
        info.update(means2d=means2d, front=index)
    # the projection's Jacobian, at the centre's direction held within 1.3 times the view's
    # half angle (3D Gaussian splatting's clamp: splats far outside the view stay finite)
    x = depth * torch.clamp(local[:, 0] / depth, -FOV_CLAMP * camera.width / (2 * fx),
                            FOV_CLAMP * camera.width / (2 * fx))
    y = depth * torch.clamp(local[:, 1] / depth, -FOV_CLAMP * camera.height / (2 * fy),
                            FOV_CLAMP * camera.height / (2 * fy))
    jacobian = depth.new_zeros(len(depth), 2, 3)
    jacobian[:, 0, 0] = fx / depth
    jacobian[:, 0, 2] = fx * x / depth ** 2
    jacobian[:, 1, 1] = -fy / depth
    jacobian[:, 1, 2] = -fy * y / depth ** 2
    transform = jacobian @ rotation.T
    projected = transform @ covariances @ transform.transpose(1, 2)
    a, b, c = projected[:, 0, 0] + LOW_PASS, projected[:, 0, 1], projected[:, 1, 1] + LOW_PASS
    determinant = a * c - b * b
    conic = torch.stack([c, -b, a], 1) / determinant[:, None]  # the inverse, per splat
    # the box around the ellipse outside which a splat's alpha is below 1/255
    opacities = opacities.index_select(0, index)
    level = torch.sqrt(2 * torch.log((255 * opacities.detach()).clamp(min=1)))
    rx, ry = level * torch.sqrt(a.detach()), level * torch.sqrt(c.detach())
    if reach is not None:
        wide = (rx > reach) | (ry > reach)
        rx, ry = rx.clamp(max=reach), ry.clamp(max=reach)
    x0 = (u.detach() - rx).floor().clamp(left, left + width)
    x1 = (u.detach() + rx).ceil().clamp(left, left + width)
    y0 = (v.detach() - ry).floor().clamp(top, top + height)
    y1 = (v.detach() + ry).ceil().clamp(top, top + height)
    shown = (x1 > x0) & (y1 > y0)
    if info is not None and reach is not None:  # cut off square: densification splits them
        info["clipped"] = index[wide & shown]
    if not shown.any():
        return None
    drawn = torch.nonzero(shown)[:, 0]
    drawn = drawn[torch.argsort(depth.detach()[drawn])]  # front to back: pairs come so
    # each splat's projection (u, v, conic, opacity), gathered with gradients only for the
    # pairs that show
    table = torch.cat([u[:, None], v[:, None], conic, opacities[:, None]], 1)
    return table, torch.stack([x0, x1, y0, y1, level], 1), index, drawn
