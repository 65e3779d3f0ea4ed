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


def edit_response(before: np.ndarray, after: np.ndarray, truth_before: np.ndarray,
                  truth_after: np.ndarray, seen: float = 0.1) -> tuple[float, float]:
    """How much of an edit a render carries where the truth says the edit shows.

    With d = after - before and d* = truth_after - truth_before, (..., 3) colours, over
    the pixels where |d*| > ``seen``: sum d . d* / sum |d*|^2, which is 1 when the render
    moves as the truth does and 0 when the edit moves nothing there (a material that the
    render gave to another channel), and the share of pixels that count.

    Examples
    --------
    >>> truth = np.zeros((2, 3)), np.array([[0.5, 0, 0], [0, 0, 0]])
    >>> edit_response(*truth, *truth), edit_response(truth[0], truth[0], *truth)
    ((1.0, 0.5), (0.0, 0.5))
    """
    moved = np.asarray(truth_after, np.float64) - truth_before
    shown = np.linalg.norm(moved, axis=-1) > seen
    if not shown.any():
        return float("nan"), 0.0
    carried = (np.asarray(after, np.float64) - before)[shown]
    return (float(np.sum(carried * moved[shown]) / np.sum(moved[shown] ** 2)),
            float(shown.mean()))
