"""ficap_ros.tools.model_build.geometry: the edge offset a border-line detector adds, rigid tag
frames, the gauge alignment and the size of a cap."""

from __future__ import annotations

import numpy as np
import pytest

from ficap_ros.tools.model_build import edge_shift_px


def test_edge_shift_moves_each_border_line_by_the_offset() -> None:
    """The builder's corner-bias model: both lines through a corner move by the offset."""
    square = np.array([[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]])
    np.testing.assert_allclose(edge_shift_px(square, 0.5), square + 0.5 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]))
    np.testing.assert_allclose(edge_shift_px(square[::-1], -0.5), (square + 0.5 * np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]))[::-1])
    # A skewed quad: every shifted edge line is parallel to the original, 0.3 px out.
    quad = np.array([[0.0, 0.0], [30.0, 4.0], [26.0, 19.0], [3.0, 15.0]])
    shifted = edge_shift_px(quad, 0.3)
    for k in range(4):
        a, b = quad[k], quad[(k + 1) % 4]
        n = np.array([b[1] - a[1], a[0] - b[0]]) / np.linalg.norm(b - a)
        n *= np.sign(np.dot((a + b) / 2 - quad.mean(axis=0), n))
        for corner in (shifted[k], shifted[(k + 1) % 4]):
            assert np.dot(corner - a, n) == pytest.approx(0.3, abs=1e-9)


def test_tag_frames_and_corners_from_params_round_trip() -> None:
    """Rigid 32 mm squares from their frames come back as the same frames."""
    from scipy.spatial.transform import Rotation

    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.tools.model_build import LOCAL_CORNERS_MM, tag_frames
    from ficap_ros.tools.model_build.geometry import corners_from_params

    nominal = nominal_model()
    r, centres = tag_frames(nominal.corners_mm)
    np.testing.assert_allclose(centres, nominal.centres_mm, atol=1e-9)
    again = corners_from_params(r.as_rotvec(), centres)
    np.testing.assert_allclose(again, nominal.corners_mm, atol=1e-9)  # the nominal tags are square
    rng = np.random.default_rng(0)
    rotvec, t_mm = rng.normal(0.0, 1.0, (5, 3)), rng.normal(0.0, 50.0, (5, 3))
    corners = corners_from_params(rotvec, t_mm)
    sides = np.linalg.norm(np.roll(corners, -1, axis=1) - corners, axis=-1)
    np.testing.assert_allclose(sides, 32.0, atol=1e-9)
    r2, c2 = tag_frames(corners)
    np.testing.assert_allclose(c2, t_mm, atol=1e-9)
    assert np.degrees((r2.inv() * Rotation.from_rotvec(rotvec)).magnitude()).max() < 1e-7
    # A slightly non-square tag gets its closest rigid square: the mean of its corners' offsets.
    noisy = corners + rng.normal(0.0, 0.05, corners.shape)
    r3, c3 = tag_frames(noisy)
    np.testing.assert_allclose(c3, noisy.mean(axis=1), atol=1e-12)
    fitted = corners_from_params(r3.as_rotvec(), c3)
    assert np.abs(fitted - corners).max() < 0.2
    assert LOCAL_CORNERS_MM.shape == (4, 3)


def test_align_model_recovers_a_rigid_motion_and_size_ratio_ignores_it() -> None:
    from scipy.spatial.transform import Rotation

    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.tools.model_build import align_model, size_ratio
    from ficap_ros.tools.model_build.geometry import rms_radius

    ref = np.array(nominal_model().corners_mm)  # writeable: scipy's apply takes no read-only array
    R = Rotation.from_euler("zyx", [30.0, -12.0, 5.0], degrees=True)
    moved = R.apply(ref.reshape(-1, 3)).reshape(ref.shape) + [4.0, -7.0, 11.0]
    T = align_model(moved, ref)  # T_ref_built: maps the moved corners back
    np.testing.assert_allclose(T.apply(moved.reshape(-1, 3)), ref.reshape(-1, 3), atol=1e-9)
    assert np.degrees((T.rotation * R).magnitude()) < 1e-9
    assert size_ratio(moved, ref) == pytest.approx(1.0, abs=1e-12)
    c = ref.reshape(-1, 3).mean(axis=0)
    assert size_ratio(c + 1.02 * (moved - c), moved) == pytest.approx(1.02, abs=1e-12)
    pts = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 3.0, 0], [0, -3.0, 0]])
    assert rms_radius(pts + 5.0) == pytest.approx(np.sqrt(5.0))
