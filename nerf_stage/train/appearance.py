"""Per-image appearance: a small colour transform of each training image after compositing,
so that exposure and white balance that change from photo to photo are not learnt as
geometry or as palette weights.

Training image i sees ``A_i rgb + b_i`` of the composited colour, with A_i (3, 3) and
b_i (3,) learnt; their mean over the images is held at the identity (the gauge: the scene
keeps the average image's appearance), and renders use the identity. On by default
(``TrainConfig.appearance``; docs/real_photos.md, "Exposure").

References
----------
R. Martin-Brualla et al. NeRF in the Wild. CVPR 2021 (an appearance code per image).
K. Rematas et al. Urban radiance fields. CVPR 2022 (an affine colour transform per image).
"""

from __future__ import annotations

import torch
from torch import nn


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
        affine = self.affine - self.affine.mean(0) + torch.eye(3, 4, device=rgb.device)
        affine = affine[image]
        return torch.einsum("bij,bj->bi", affine[..., :3], rgb) + affine[..., 3]
