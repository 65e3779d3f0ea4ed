"""Shared fixtures: seeded generators and tiny images written to disk."""

import numpy as np
import pytest
from PIL import Image


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def photo_dir(tmp_path, rng):
    """A folder of three small colourful images of different sizes, one in a subfolder."""
    folder = tmp_path / "photos"
    (folder / "sub").mkdir(parents=True)
    for name, (h, w) in [("a.png", (12, 16)), ("b.jpg", (10, 9)), ("sub/c.png", (7, 11))]:
        yy, xx = np.mgrid[0:h, 0:w]
        img = np.stack([xx / w, yy / h, rng.random((h, w))], -1)
        Image.fromarray((img * 255).astype(np.uint8)).save(folder / name)
    return folder
