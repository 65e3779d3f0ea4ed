"""Training losses of weight NeRFs: colours as a camera records them, weights (tone-mapped
for transport), the Cauchy sparsity prior on optical thickness, and the distortion loss
that gathers each ray's weight where it ends."""

from __future__ import annotations

import torch

from palette_core.basis import Basis

from ..fields.base import tone_map

SPARSITY_SCALE = 0.01  # optical thickness of a step where the sparsity prior bends


def recorded_rgb_loss(rgb: torch.Tensor, images: torch.Tensor) -> torch.Tensor:
    """L2 of (R, 3) colours through the weights against the images, as a camera records them:
    clipped at 1, so that a lamp of radiance 30 is not pulled down to the image's 1 (which
    would move its weight onto the materials' channels)."""
    return torch.mean((rgb.clamp(max=1) - images) ** 2)


def sparsity_loss(optical: torch.Tensor) -> torch.Tensor:
    """Cauchy sparsity prior: mean of log(1 + (tau / SPARSITY_SCALE)^2) over the (P,) optical
    thicknesses tau of the samples (the sparsity prior of Plenoxels, Fridovich-Keil et al.
    CVPR 2022, on thickness rather than density): steep for thin fog, flat for opaque
    surfaces; 0 for no samples."""
    return torch.log1p((optical / SPARSITY_SCALE) ** 2).sum() / max(1, len(optical))


def distortion_loss(ray: torch.Tensor, t: torch.Tensor, weight: torch.Tensor, step: float,
                    rays: int) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss (Barron et al. CVPR 2022, eq. 15), mean over ``rays``
    rays: sum_ij w_i w_j |t_i - t_j| + 1/3 sum_i w_i^2 step for the (P,) samples at ``t``
    (intervals of length ``step``) with compositing weights w, packed by ``ray`` in
    ascending order and along each ray. It is small when a ray's weight sits in one short
    stretch, so floaters in front of the surfaces cost. Linear time: the pairs come from
    each ray's running sums of w and w t (as DVGO v2 computes it)."""
    if len(t) == 0:
        return weight.sum()
    total_w, total_wt = torch.cumsum(weight, 0), torch.cumsum(weight * t, 0)
    first = torch.searchsorted(ray, ray)  # each sample's ray starts here
    before_w = total_w - weight - (total_w - weight)[first]
    before_wt = total_wt - weight * t - (total_wt - weight * t)[first]
    pairs = 2 * (weight * (t * before_w - before_wt)).sum()
    return (pairs + (weight ** 2).sum() * step / 3) / max(1, rays)


def depth_loss(ray: torch.Tensor, t: torch.Tensor, weight: torch.Tensor,
               targets: torch.Tensor) -> torch.Tensor:
    """Mean over the (R,) rays with ``targets`` of sum_i w_i (t_i - target)^2, for the (P,)
    samples at ``t`` with compositing weights w of rays ``ray`` (DS-NeRF's ray-termination
    prior with a vanishing spread): every bit of a ray's weight away from where its sparse
    point lies costs, floaters in front of it most."""
    return (weight * (t - targets[ray]) ** 2).sum() / max(1, len(targets))


def weight_loss(kind: str, values: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """L2 of (R, M) premultiplied weights; transport weights are tone-mapped first
    (``fields.base.tone_map``), so that emitters do not drown the rest."""
    if kind == Basis.TRANSPORT:
        values, targets = tone_map(values), tone_map(targets)
    return torch.mean((values - targets) ** 2)


def ssim_loss(image: torch.Tensor, truth: torch.Tensor, window: int = 11,
              sigma: float = 1.5) -> torch.Tensor:
    """1 - SSIM of (H, W, C) images in [0, 1], with a Gaussian window (Wang et al. IEEE TIP
    2004, as 3D Gaussian splatting trains with it): the structure that L1 alone blurs. The
    window is separable: the five local moments are blurred together, a row and a column
    pass of ``window`` taps each instead of ``window``^2."""
    x = torch.arange(window, dtype=image.dtype, device=image.device) - window // 2
    kernel = torch.exp(-x ** 2 / (2 * sigma ** 2))
    kernel = kernel / kernel.sum()
    a, b = image.permute(2, 0, 1)[None], truth.permute(2, 0, 1)[None]
    moments = torch.cat([a, b, a * a, b * b, a * b], 1)
    n, pad = moments.shape[1], window // 2
    rows = kernel.view(1, 1, 1, window).expand(n, 1, 1, window)
    blurred = torch.nn.functional.conv2d(moments, rows, padding=(0, pad), groups=n)
    blurred = torch.nn.functional.conv2d(blurred, rows.transpose(2, 3), padding=(pad, 0),
                                         groups=n)
    mean_a, mean_b, aa, bb, ab = blurred.split(a.shape[1], 1)
    var_a, var_b = aa - mean_a ** 2, bb - mean_b ** 2
    cov = ab - mean_a * mean_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    ssim = ((2 * mean_a * mean_b + c1) * (2 * cov + c2)
            / ((mean_a ** 2 + mean_b ** 2 + c1) * (var_a + var_b + c2)))
    return 1 - ssim.mean()
