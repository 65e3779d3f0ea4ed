"""Image metrics: PSNR and SSIM (scikit-image) of images in [0, 1]. No torch, no path
tracer: importing a metric costs numpy and scikit-image only."""

from __future__ import annotations

import math

import numpy as np


def psnr_from_mse(mse: float) -> float:
    """Peak signal-to-noise ratio in dB of a mean squared error of values in [0, 1]."""
    return float("inf") if mse == 0 else -10 * math.log10(mse)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB of images in [0, 1]."""
    return psnr_from_mse(float(np.mean((np.asarray(a, np.float64) - b) ** 2)))


def image_scores(predicted: np.ndarray, truth: np.ndarray) -> dict:
    """Mean PSNR and SSIM (scikit-image) of (N, H, W, 3) images against the truth."""
    from skimage.metrics import structural_similarity

    return {
        "psnr": float(np.mean([psnr(p, t) for p, t in zip(predicted, truth)])),
        "ssim": float(np.mean([structural_similarity(p, t, channel_axis=-1, data_range=1.0)
                               for p, t in zip(predicted, truth)])),
    }
