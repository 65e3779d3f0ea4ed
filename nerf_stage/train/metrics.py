"""Image metrics: PSNR (plain and colour-corrected) and SSIM (scikit-image) of images in
[0, 1], the edit response, and camera pose errors. No torch, no path tracer: importing a
metric costs numpy and scikit-image only."""

from __future__ import annotations

import math

import numpy as np


def psnr_from_mse(mse: float) -> float:
    """Peak signal-to-noise ratio in dB of a mean squared error of values in [0, 1]."""
    return float("inf") if mse == 0 else -10 * math.log10(mse)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB of images in [0, 1]."""
    return psnr_from_mse(float(np.mean((np.asarray(a, np.float64) - b) ** 2)))


def image_scores(predicted: np.ndarray, truth: np.ndarray,
                 corrected: bool = False) -> dict:
    """Mean PSNR and SSIM (scikit-image) of (N, H, W, 3) images against the truth; with
    ``corrected``, also the mean PSNR of each image ``colour_corrected`` (``psnr_cc``)."""
    from skimage.metrics import structural_similarity

    scores = {
        "psnr": float(np.mean([psnr(p, t) for p, t in zip(predicted, truth)])),
        "ssim": float(np.mean([structural_similarity(p, t, channel_axis=-1, data_range=1.0)
                               for p, t in zip(predicted, truth)])),
    }
    if corrected:
        scores["psnr_cc"] = float(np.mean([psnr(colour_corrected(p, t), t)
                                           for p, t in zip(predicted, truth)]))
    return scores


def colour_corrected(predicted: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(H, W, 3) ``predicted`` through the affine colour map (3 x 3 and an offset) that maps
    it closest to ``truth`` by least squares, in [0, 1]: a render as the photo's own exposure
    and white balance would have recorded it, had they been learned as a training photo's are
    (``appearance.Appearance``: the same maps). A held-out photo's are not known: scored so,
    a capture whose camera set its exposure photo by photo scores what the model draws, not
    how near one photo's exposure came to the training photos'. (gsplat scores runs that
    learn appearance so, with Mip-NeRF 360's quadratic map.)

    Examples
    --------
    >>> truth = np.random.default_rng(0).random((4, 4, 3))
    >>> bool(np.allclose(colour_corrected(0.5 * truth + 0.1, truth), truth))
    True
    """
    flat = np.asarray(predicted, np.float64).reshape(-1, 3)
    terms = np.concatenate([flat, np.ones((len(flat), 1))], 1)
    colour_map = np.linalg.lstsq(terms, np.asarray(truth, np.float64).reshape(-1, 3),
                                 rcond=None)[0]
    return np.clip(terms @ colour_map, 0, 1).reshape(np.shape(predicted))


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


def pose_errors(poses: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Errors of (N, 4, 4) camera-to-world ``poses`` against the ``truth``'s, after the
    similarity that best maps the estimated camera centres onto the true ones (Umeyama,
    PAMI 1991): (N,) rotation errors in degrees and (N,) centre errors in the truth's units.

    Examples
    --------
    >>> truth = np.tile(np.eye(4), (3, 1, 1)); truth[:, :3, 3] = np.eye(3)
    >>> moved = truth.copy(); moved[:, :3, 3] = 2 * truth[:, :3, 3] + 5  # scaled and shifted
    >>> [float(e.max().round(9)) for e in pose_errors(moved, truth)]
    [0.0, 0.0]
    """
    a, b = poses[:, :3, 3], truth[:, :3, 3]
    a0, b0 = a - a.mean(0), b - b.mean(0)
    u, sigma, vt = np.linalg.svd(b0.T @ a0 / len(a))
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ flip @ vt
    scale = float(np.trace(np.diag(sigma) @ flip) / max((a0 ** 2).sum() / len(a), 1e-300))
    centres = scale * a0 @ rotation.T + b.mean(0)
    relative = np.einsum("nji,njk->nik", truth[:, :3, :3], rotation @ poses[:, :3, :3])
    cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return np.degrees(np.arccos(cos)), np.linalg.norm(centres - b, axis=1)
