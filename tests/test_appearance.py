"""gdiff.appearance: the exposure and white-balance gain between two views of one scene."""

import numpy as np
import pytest

from gdiff.appearance import median_gain


def test_median_gain_is_the_exposure_a_minority_change_does_not_move():
    """A faintly textured wall, and the same view one stop brighter in red, unchanged in
    green, one stop darker in blue, with a tenth of it covered by a new, saturated object: the
    gain from the first to the second is (2, 1, 0.5), within the wall's spread.
    A black channel is divided by the floor, not by zero."""
    rng = np.random.default_rng(3)
    a = rng.uniform(0.2, 0.24, (60, 90, 3)).astype(np.float32)
    b = a * np.array([2.0, 1.0, 0.5], np.float32)
    b[:6] = (0.9, 0.05, 0.9)  # the new object
    g = median_gain(b, a)
    assert g.dtype == np.float32 and g.shape == (3,)
    assert g == pytest.approx([2.0, 1.0, 0.5], rel=0.1)
    plain = np.median(b.reshape(-1, 3), 0) / np.median(a.reshape(-1, 3), 0)
    assert g == pytest.approx(plain, rel=1e-6)  # the ratio of the channel medians
    assert median_gain(b[:, :, :1].repeat(3, -1), np.zeros_like(a), 0.01) == pytest.approx(
        np.median(b[..., 0]) / 0.01, rel=1e-6)
