"""Splats projected into a view: each splat's screen centre, the inverse of its projected
covariance (EWA splatting's Jacobian, Mip-Splatting's 2D filter), its peak opacity, and
the box of pixels its ellipse at alpha 1/255 may touch; what both ways of drawing them
(``tiles`` on a CPU, ``pairs`` in PyTorch) start from. On CUDA in PyTorch; on a CPU, every
splat at once in numba, forward and backward (``_CpuProjection``: gsplat's fused
projection, where PyTorch's small batched products cost more than the drawing).

References
----------
B. Kerbl et al. 3D Gaussian splatting for real-time radiance field rendering. SIGGRAPH
2023 (projection of the covariances, the low-pass filter, the Jacobian's clamp).
M. Zwicker et al. EWA splatting. IEEE TVCG 8(3), 2002.
Z. Yu et al. Mip-Splatting: alias-free 3D Gaussian splatting. CVPR 2024 (the 2D filter).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

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
    if centres.is_cuda:
        means2d, rest, box, index, depth, wide = _projected(centres, covariances, opacities,
                                                            pose, camera, reach, window)
    else:
        means2d, rest, box, index, depth, wide = _CpuProjection.apply(
            centres, covariances, opacities, pose, camera, reach, window)
    if info is not None and means2d.requires_grad:
        means2d.retain_grad()
        info.update(means2d=means2d, front=index)
    shown = (box[:, 1] > box[:, 0]) & (box[:, 3] > box[:, 2])
    if info is not None and reach is not None:  # cut off square: densification splits them
        info["clipped"] = index[wide & shown]
    if not shown.any():
        return None
    drawn = torch.nonzero(shown)[:, 0]
    drawn = drawn[torch.argsort(depth[drawn])]  # front to back: pairs come so
    return torch.cat([means2d, rest], 1), box, index, drawn


def _view(camera: Intrinsics) -> tuple[float, ...]:
    """The camera's focal lengths, centre and the Jacobian's clamp (``FOV_CLAMP``) of the
    centres' directions: fx, fy, cx, cy, x limit, y limit."""
    return (camera.fx, camera.fy, camera.cx, camera.cy,
            FOV_CLAMP * camera.width / (2 * camera.fx),
            FOV_CLAMP * camera.height / (2 * camera.fy))


def _projected(centres, covariances, opacities, pose, camera: Intrinsics, reach, window):
    """``project``'s parts in PyTorch: (F, 2) centres u, v and (F, 4) inverse covariance and
    opacity (with gradients), (F, 5) box, (F,) splat index and depth, (F,) wider than
    ``reach``."""
    pose = pose.to(centres.dtype)
    rotation, origin = pose[:3, :3], pose[:3, 3]
    local = (centres - origin) @ rotation  # camera axes: x right, y up, looking down -z
    depth = -local[:, 2]
    index = torch.nonzero(depth > NEAR)[:, 0]
    local, depth = local.index_select(0, index), depth.index_select(0, index)
    covariances = covariances.index_select(0, index)
    fx, fy, cx, cy, limit_x, limit_y = _view(camera)
    u = cx + fx * local[:, 0] / depth
    v = cy - fy * local[:, 1] / depth
    # the projection's Jacobian, at the centre's direction held within 1.3 times the view's
    # half angle (3D Gaussian splatting's clamp: splats far outside the view stay finite)
    x = depth * torch.clamp(local[:, 0] / depth, -limit_x, limit_x)
    y = depth * torch.clamp(local[:, 1] / depth, -limit_y, limit_y)
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
    opacities = opacities.index_select(0, index)
    box, wide = _box(u.detach(), v.detach(), a.detach(), c.detach(), opacities.detach(),
                     reach, window)
    return (torch.stack([u, v], 1), torch.cat([conic, opacities[:, None]], 1), box, index,
            depth.detach(), wide)


def _box(u, v, a, c, opacities, reach, window):
    """(F, 5) box x0, x1, y0, y1 around each ellipse outside which its alpha is below 1/255
    (cut at ``reach``), and its level; (F,) whether it was cut."""
    left, top, width, height = window
    level = torch.sqrt(2 * torch.log((255 * opacities).clamp(min=1)))
    rx, ry = level * torch.sqrt(a), level * torch.sqrt(c)
    wide = torch.zeros_like(rx, dtype=torch.bool)
    if reach is not None:
        wide = (rx > reach) | (ry > reach)
        rx, ry = rx.clamp(max=reach), ry.clamp(max=reach)
    x0 = (u - rx).floor().clamp(left, left + width)
    x1 = (u + rx).ceil().clamp(left, left + width)
    y0 = (v - ry).floor().clamp(top, top + height)
    y1 = (v + ry).ceil().clamp(top, top + height)
    return torch.stack([x0, x1, y0, y1, level], 1), wide


class _CpuProjection(torch.autograd.Function):
    """``_projected`` on a CPU: every splat in numba (``_project_forward``, float64), and
    its backward (``_project_backward``) into the centres, covariances and opacities."""

    @staticmethod
    def forward(ctx, centres, covariances, opacities, pose, camera, reach, window):
        pose = pose.double().numpy()
        view = np.array(_view(camera))
        arrays = (centres.detach().numpy(), covariances.detach().numpy(), pose[:3, :3],
                  pose[:3, 3].copy(), view)
        out, front = np.empty((len(centres), 8)), np.zeros(len(centres), np.bool_)
        _project_forward(*arrays, NEAR, LOW_PASS, front, out)
        index = torch.from_numpy(np.flatnonzero(front))
        rows = torch.from_numpy(out[index.numpy()]).to(centres.dtype)
        opacity = opacities.detach().index_select(0, index)
        box, wide = _box(rows[:, 0], rows[:, 1], rows[:, 6], rows[:, 7], opacity, reach,
                         window)
        ctx.save_for_backward(index)
        ctx.arrays, ctx.sizes = arrays, (len(centres), opacities.shape)
        depth = rows[:, 5].contiguous()
        ctx.mark_non_differentiable(box, index, depth, wide)
        return (rows[:, :2].contiguous(), torch.cat([rows[:, 2:5], opacity[:, None]], 1), box,
                index, depth, wide)

    @staticmethod
    def backward(ctx, grad_means2d, grad_rest, *_):
        (index,), (splats, shape) = ctx.saved_tensors, ctx.sizes
        grad_centres, grad_covariances = np.zeros((splats, 3)), np.zeros((splats, 3, 3))
        rows = np.concatenate([grad_means2d.double().numpy(), grad_rest[:, :3].double().numpy()],
                              1)
        _project_backward(*ctx.arrays, LOW_PASS, index.numpy(), rows, grad_centres,
                          grad_covariances)
        dtype = grad_rest.dtype
        grad_opacities = grad_rest.new_zeros(shape).index_copy_(0, index, grad_rest[:, 3])
        return (torch.from_numpy(grad_centres).to(dtype),
                torch.from_numpy(grad_covariances).to(dtype), grad_opacities,
                None, None, None, None)


@njit(cache=True, inline="always")
def _camera(centre, rotation, origin):
    """``centre``'s camera coordinates x, y (right, up) and its depth."""
    x = y = z = 0.0
    for k in range(3):
        offset = centre[k] - origin[k]
        x += offset * rotation[k, 0]
        y += offset * rotation[k, 1]
        z += offset * rotation[k, 2]
    return x, y, -z


@njit(cache=True)
def _transform(x, y, depth, rotation, view):
    """The rows (3,) and (3,) of the projection's Jacobian J at camera coordinates (x, y,
    depth), its direction held within the clamp (``FOV_CLAMP``), times the view's
    rotation^T; J's x and y, and whether each was clamped."""
    fx, fy, limit_x, limit_y = view[0], view[1], view[4], view[5]
    ratio_x, ratio_y = x / depth, y / depth
    tx = depth * min(max(ratio_x, -limit_x), limit_x)
    ty = depth * min(max(ratio_y, -limit_y), limit_y)
    a0, a2 = fx / depth, fx * tx / depth ** 2
    b1, b2 = -fy / depth, -fy * ty / depth ** 2
    first = (a0 * rotation[0, 0] + a2 * rotation[0, 2], a0 * rotation[1, 0] + a2 * rotation[1, 2],
             a0 * rotation[2, 0] + a2 * rotation[2, 2])
    second = (b1 * rotation[0, 1] + b2 * rotation[0, 2], b1 * rotation[1, 1] + b2 * rotation[1, 2],
              b1 * rotation[2, 1] + b2 * rotation[2, 2])
    return first, second, tx, ty, abs(ratio_x) > limit_x, abs(ratio_y) > limit_y


@njit(cache=True, parallel=True)
def _project_forward(centres, covariances, rotation, origin, view, near, low_pass, front, out):
    """For each splat: ``front`` (S,) whether its depth is beyond ``near``, and ``out`` (S, 8)
    u, v, the inverse covariance a, b, c, depth, and the projected covariance's a and c
    (``low_pass`` added to both: the box's)."""
    fx, fy, cx, cy = view[0], view[1], view[2], view[3]
    for s in prange(len(centres)):
        x, y, depth = _camera(centres[s], rotation, origin)
        if not depth > near:
            continue
        front[s] = True
        first, second, _, _, _, _ = _transform(x, y, depth, rotation, view)
        a, b, c = _projected_covariance(first, second, covariances[s])
        a, c = a + low_pass, c + low_pass
        determinant = a * c - b * b
        out[s, 0], out[s, 1] = cx + fx * x / depth, cy - fy * y / depth
        out[s, 2], out[s, 3], out[s, 4] = c / determinant, -b / determinant, a / determinant
        out[s, 5], out[s, 6], out[s, 7] = depth, a, c


@njit(cache=True, inline="always")
def _projected_covariance(first, second, sigma):
    """a, b, c of the 2 x 2 T Sigma T^T, T's rows ``first`` and ``second``."""
    a = b = c = 0.0
    for k in range(3):
        for n in range(3):
            a += first[k] * sigma[k, n] * first[n]
            b += first[k] * sigma[k, n] * second[n]
            c += second[k] * sigma[k, n] * second[n]
    return a, b, c


@njit(cache=True, parallel=True)
def _project_backward(centres, covariances, rotation, origin, view, low_pass, index, grad,
                      grad_centres, grad_covariances):
    """The gradients of ``_project_forward``'s u, v and inverse covariance (``grad`` (F, 5),
    the splats ``index`` (F,)) into ``grad_centres`` (S, 3) and ``grad_covariances``
    (S, 3, 3): through the inverse, T Sigma T^T, T = J R^T (J's clamp included) and the
    camera coordinates."""
    fx, fy = view[0], view[1]
    for f in prange(len(index)):
        s = index[f]
        sigma = covariances[s]
        x, y, depth = _camera(centres[s], rotation, origin)
        first, second, tx, ty, clamp_x, clamp_y = _transform(x, y, depth, rotation, view)
        a, b, c = _projected_covariance(first, second, sigma)
        a, c = a + low_pass, c + low_pass
        determinant = a * c - b * b
        i00, i01, i11 = c / determinant, -b / determinant, a / determinant
        # d inverse = -inverse dM inverse: dM = -inverse G inverse, G the symmetric gradient
        g00, g01, g11 = grad[f, 2], 0.5 * grad[f, 3], grad[f, 4]
        h00, h01 = g00 * i00 + g01 * i01, g00 * i01 + g01 * i11  # G inverse
        h10, h11 = g01 * i00 + g11 * i01, g01 * i01 + g11 * i11
        m00 = -(i00 * h00 + i01 * h10)
        m01 = -(i00 * h01 + i01 * h11)
        m11 = -(i01 * h01 + i11 * h11)
        # dM T by rows (p, q); Sigma's gradient T^T dM T; T's 2 dM T Sigma
        p0, p1, p2 = (m00 * first[0] + m01 * second[0], m00 * first[1] + m01 * second[1],
                      m00 * first[2] + m01 * second[2])
        q0, q1, q2 = (m01 * first[0] + m11 * second[0], m01 * first[1] + m11 * second[1],
                      m01 * first[2] + m11 * second[2])
        p, q = (p0, p1, p2), (q0, q1, q2)
        for k in range(3):
            for n in range(3):
                grad_covariances[s, k, n] = first[k] * p[n] + second[k] * q[n]
        # J's gradient dT R: J00 = fx / d, J02 = fx tx / d^2, J11 = -fy / d, J12 = -fy ty / d^2
        j00 = j02 = j11 = j12 = 0.0
        for k in range(3):
            grad_first = 2.0 * (p[0] * sigma[0, k] + p[1] * sigma[1, k] + p[2] * sigma[2, k])
            grad_second = 2.0 * (q[0] * sigma[0, k] + q[1] * sigma[1, k] + q[2] * sigma[2, k])
            j00 += grad_first * rotation[k, 0]
            j02 += grad_first * rotation[k, 2]
            j11 += grad_second * rotation[k, 1]
            j12 += grad_second * rotation[k, 2]
        grad_tx, grad_ty = j02 * fx / depth ** 2, -j12 * fy / depth ** 2
        grad_depth = (-j00 * fx / depth ** 2 - 2.0 * j02 * fx * tx / depth ** 3
                      + j11 * fy / depth ** 2 + 2.0 * j12 * fy * ty / depth ** 3)
        grad_x, grad_y = 0.0, 0.0
        if clamp_x:
            grad_depth += grad_tx * tx / depth
        else:
            grad_x += grad_tx
        if clamp_y:
            grad_depth += grad_ty * ty / depth
        else:
            grad_y += grad_ty
        # u = cx + fx x / d, v = cy - fy y / d
        grad_x += grad[f, 0] * fx / depth
        grad_y -= grad[f, 1] * fy / depth
        grad_depth += -grad[f, 0] * fx * x / depth ** 2 + grad[f, 1] * fy * y / depth ** 2
        for k in range(3):  # (x, y, -depth) = (centre - origin) R
            grad_centres[s, k] = (grad_x * rotation[k, 0] + grad_y * rotation[k, 1]
                                  - grad_depth * rotation[k, 2])
