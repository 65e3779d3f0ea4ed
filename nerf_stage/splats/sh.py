"""Real spherical harmonics up to degree 3, as 3D Gaussian splatting evaluates them: a
splat's view-dependent values are ``sh_basis(d) @ coefficients`` for the unit direction d
from the camera to the splat.

References
----------
P.-P. Sloan. Stupid spherical harmonics (SH) tricks. GDC 2008 (the constants).
B. Kerbl et al. 3D Gaussian splatting for real-time radiance field rendering. SIGGRAPH
2023 (``eval_sh``: the order and signs of the coefficients, which PLY viewers share).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

MAX_DEGREE = 3
#: The degree-0 constant: a colour c is stored as (c - 0.5) / SH_C0.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_terms(degree: int) -> int:
    """Coefficients of degrees 0 to ``degree``: (degree + 1)^2."""
    return (degree + 1) ** 2


def sh_basis(directions: torch.Tensor, degree: int) -> torch.Tensor:
    """(N, (degree + 1)^2) basis functions at (N, 3) unit ``directions``."""
    x, y, z = directions.unbind(-1)
    terms = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        terms += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        terms += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy),
                  SH_C2[3] * x * z, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        terms += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z,
                  SH_C3[2] * y * (4 * zz - xx - yy), SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                  SH_C3[4] * x * (4 * zz - xx - yy), SH_C3[5] * z * (xx - yy),
                  SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(terms, -1)


def sh_values(basis: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
    """(S, C) values ``basis`` (S, B') x the first B' of the (S, B, C) ``coefficients``: a
    batched product of a row and a small matrix per splat, on a CPU in numba
    (``_CpuContraction``), where PyTorch's batched products cost more than the
    arithmetic."""
    if basis.is_cuda:
        return torch.einsum("sb,sbc->sc", basis, coefficients[:, :basis.shape[1]])
    return _CpuContraction.apply(basis, coefficients)


class _CpuContraction(torch.autograd.Function):
    """``sh_values`` on a CPU, forward and backward."""

    @staticmethod
    def forward(ctx, basis, coefficients):
        arrays = (basis.detach().numpy(), coefficients.detach().numpy())
        ctx.arrays = arrays
        out = np.empty((len(basis), coefficients.shape[2]), arrays[1].dtype)
        _contract(*arrays, out)
        return torch.from_numpy(out).to(coefficients.dtype)

    @staticmethod
    def backward(ctx, grad):
        basis, coefficients = ctx.arrays
        grad_basis, grad_coefficients = np.empty_like(basis), np.zeros_like(coefficients)
        _contract_backward(basis, coefficients, np.ascontiguousarray(grad.numpy()), grad_basis,
                           grad_coefficients)
        return (torch.from_numpy(grad_basis).to(grad.dtype),
                torch.from_numpy(grad_coefficients).to(grad.dtype))


@njit(cache=True, parallel=True)
def _contract(basis, coefficients, out):
    """``out`` (S, C): each splat's basis row times its coefficients."""
    for s in prange(len(basis)):
        for c in range(coefficients.shape[2]):
            total = 0.0
            for b in range(basis.shape[1]):
                total += basis[s, b] * coefficients[s, b, c]
            out[s, c] = total


@njit(cache=True, parallel=True)
def _contract_backward(basis, coefficients, grad, grad_basis, grad_coefficients):
    """d/d basis: the gradient times each coefficient row; d/d coefficients: the basis
    times the gradient (zero past B')."""
    for s in prange(len(basis)):
        for b in range(basis.shape[1]):
            total = 0.0
            for c in range(coefficients.shape[2]):
                total += grad[s, c] * coefficients[s, b, c]
                grad_coefficients[s, b, c] = grad[s, c] * basis[s, b]
            grad_basis[s, b] = total
