"""Motion blur's shared corner errors: the modes of a tag moving over the exposure."""

from __future__ import annotations

import numpy as np

from ficap_ros.vision.motion_blur import blur_modes


def test_blur_modes_shrink_across_the_motion_and_shift_along_it() -> None:
    """A square tag moving 4 px along x: ``blur`` moves the corners toward the centre along x
    by the length times the cosine of their lever to the motion, ``blur_shift`` every corner by
    the motion itself."""
    square = np.array([[[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]])
    modes = blur_modes(square, np.array([[4.0, 0.0]]))
    cos = np.sqrt(0.5)
    np.testing.assert_allclose(modes["blur"].reshape(4, 2),
                               [[4 * cos, 0.0], [-4 * cos, 0.0], [-4 * cos, 0.0], [4 * cos, 0.0]])
    np.testing.assert_allclose(modes["blur_shift"].reshape(4, 2), [[4.0, 0.0]] * 4)
