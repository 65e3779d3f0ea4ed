"""Assertions shared by the tests."""

import numpy as np


def weight_invariants(weights, palette, colours):
    """Assert the invariants every weight vector satisfies (docs/formats.md)."""
    from palette_core.constants import WEIGHT_MIN, WEIGHT_SUM_TOL

    weights = np.asarray(weights, np.float64)
    assert not np.isnan(weights).any()
    assert weights.min() >= WEIGHT_MIN
    assert np.abs(weights.sum(-1) - 1).max() < WEIGHT_SUM_TOL
    if colours is not None:
        assert np.abs(weights @ palette - colours).max() < 1e-6


def expect_error(main, argv, message, capsys):
    """Assert that a CLI exits 2 with one line on stderr containing ``message``."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
