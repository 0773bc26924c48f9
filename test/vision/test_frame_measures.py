"""Tests of ficap_ros.vision.frame_measures: what a frame shows of its tags' shared corner errors."""

from __future__ import annotations

import numpy as np
import pytest

from ficap_ros.vision.frame_measures import (
    edge_shift_mean_px,
    light_gradient_px,
    shared_bias_ratio,
)


def test_light_gradient_px() -> None:
    rng = np.random.default_rng(2)
    centres = rng.uniform(0.0, 400.0, (15, 2))
    plane = 0.2 + 0.5 * (centres[:, 0] - centres[:, 0].mean()) / np.ptp(centres, axis=0).max()
    assert light_gradient_px(plane, centres) == pytest.approx(np.std(plane), rel=1e-9)
    assert light_gradient_px(np.full(15, 0.4), centres) == pytest.approx(0.0, abs=1e-12)
    few = np.full(15, np.nan)
    few[:5] = plane[:5]
    assert light_gradient_px(few, centres) == 0.0  # too few fitted tags to tell a gradient


def test_edge_shift_mean_px() -> None:
    """The fitted tags' mean edge shift: NaN (not fitted) left out; none fitted or unknown: 0."""
    assert edge_shift_mean_px(np.array([0.2, np.nan, 0.5, -0.1])) == pytest.approx(0.2, rel=1e-12)
    assert edge_shift_mean_px(np.array([np.nan, np.nan])) == 0.0
    assert edge_shift_mean_px(None) == 0.0


def test_shared_bias_ratio() -> None:
    """The frame's corner noise over its cell width: the median tag's noise over the median tag's
    side / 8 cells."""
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    corners = np.stack([40.0 * square, 48.0 * square + 100.0, 32.0 * square + 300.0])
    assert shared_bias_ratio(corners, np.array([0.3, 0.1, 0.2])) == pytest.approx(0.2 / 5.0, rel=1e-12)
    # A tag seen obliquely (half as wide): its mean side is 3/4 of the square's.
    oblique = 40.0 * square * np.array([0.5, 1.0])
    assert shared_bias_ratio(oblique[None], np.array([0.15])) == pytest.approx(0.15 / 3.75, rel=1e-12)
