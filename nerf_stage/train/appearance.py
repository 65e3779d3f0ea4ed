"""Per-image appearance: a small colour transform of each training image after compositing,
so that exposure and white balance that change from photo to photo are not learnt as
geometry or as palette weights.

Training image i sees ``A_i rgb + b_i`` of the composited colour, with A_i (3, 3) and
b_i (3,) learnt; their mean over the images is held at the identity (the gauge: the scene
keeps the average image's appearance), and renders use the identity. On by default
(``TrainConfig.appearance``; docs/decisions/0008-per-image-appearance.md).

The palette stage asks for the weights of each pixel's colour with its image's transform
undone (``exposure_free_weights``, computed again as the transforms go on learning): the
stack's weights were decomposed from the photos as recorded, exposure included, and would
pull the weights back towards every photo's own exposure.

References
----------
R. Martin-Brualla et al. NeRF in the Wild. CVPR 2021 (an appearance code per image).
K. Rematas et al. Urban radiance fields. CVPR 2022 (an affine colour transform per image).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from palette_core import Basis
from palette_core.stack import WeightStack
from palette_core.weights import per_colour, stack_colour_weights


class Appearance(nn.Module):
    """The affine colour transforms of ``images`` training images, (images, 3, 4)."""

    def __init__(self, images: int):
        super().__init__()
        self.affine = nn.Parameter(torch.eye(3, 4).repeat(images, 1, 1))

    def forward(self, rgb: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """(B, 3) composited colours of pixels of training images ``image`` (B,) -> (B, 3)
        as those images recorded them.

        Examples
        --------
        >>> Appearance(2)(torch.tensor([[0.2, 0.5, 0.9]]), torch.tensor([1]))
        tensor([[0.2000, 0.5000, 0.9000]], grad_fn=<AddBackward0>)
        """
        # gathered by index_select: its backward adds into the (images, 3, 4) rows, where an
        # advanced index's would sort a whole view's pixels, all of one image, on a GPU
        affine = self.transforms().index_select(0, image)
        return torch.einsum("bij,bj->bi", affine[..., :3], rgb) + affine[..., 3]

    def transforms(self) -> torch.Tensor:
        """(images, 3, 4) the transforms, their mean held at the identity."""
        return self.affine - self.affine.mean(0) + torch.eye(3, 4, device=self.affine.device)

    @torch.no_grad()
    def undo(self, recorded: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
        """(B, 3) colours as training images ``image`` (B,) recorded them -> (B, 3) the
        composited colours that ``forward`` maps to them."""
        affine = self.transforms()
        inverse = torch.linalg.inv(affine[:, :, :3])[image]
        return torch.einsum("bij,bj->bi", inverse, recorded - affine[image, :, 3])


def exposure_free_weights(appearance: Appearance, stack: WeightStack, rgb: torch.Tensor,
                          image: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor | None:
    """(B, K) weight targets of training pixels of (B, 3) colours ``rgb`` and (B,) ``alpha``
    in training images ``image`` (B,): the stack's weights (premultiplied by alpha) of the
    colours with their image's transform undone. None where the stack's weights cannot be
    computed again for other colours (the transport basis, spatial or simulated weights)."""
    if stack.basis != Basis.ADDITIVE or not per_colour(stack.method):
        return None
    colours = appearance.undo(rgb, image).clamp(0, 1).double().cpu().numpy()
    weights = stack_colour_weights(stack, colours)
    return torch.as_tensor(weights.astype(np.float32), device=rgb.device) * alpha[:, None]
