"""ficap_ros.tools.synth.raster: faces drawn through exact homographies, back faces culled, the head
hiding what is behind it by its depth."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from synth_frames import MODEL, detect

from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.tools.synth import RenderConfig, default_scene, render
from ficap_ros.tools.synth.raster import homography


@given(st.lists(st.floats(-40.0, 40.0), min_size=8, max_size=8))
def test_homography_maps_the_four_points_exactly(offsets: list[float]) -> None:
    src = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0], [0.0, 100.0]])
    dst = src * 3.0 + 500.0 + np.reshape(offsets, (4, 2))
    H = homography(src, dst)
    mapped = np.c_[src, np.ones(4)] @ H.T
    np.testing.assert_allclose(mapped[:, :2] / mapped[:, 2:], dst, atol=1e-9)
    assert H[2, 2] == 1.0
    # OpenCV's own solution (float32 inside) agrees to its precision.
    cv = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
    np.testing.assert_allclose(H, cv / cv[2, 2], rtol=1e-4, atol=1e-6)


def test_back_faces_never_reported() -> None:
    scene = default_scene("540p")
    for yaw in (-80.0, 0.0, 55.0):
        T = scene.cap_pose(rotation_from_ypr_deg(yaw, -10.0, 0.0))
        frame = render(MODEL, scene.camera, T, RenderConfig(noise=False), seed=0)
        normals = T.rotation.apply(MODEL.normals)
        centres = T.apply(MODEL.centres_mm / 1000.0)
        facing = {t for t, n, c in zip(MODEL.ids, normals, centres) if n @ c < 0}
        assert set(frame.corners_px) == facing == set(frame.visible_fraction)
        assert len(facing) >= 5
        if abs(yaw) > 45:
            assert len(facing) < len(MODEL) - 5
        assert not set(detect(frame.image)) - facing


def test_occluder_hides_faces_at_large_yaw() -> None:
    scene = default_scene("540p")
    T = scene.cap_pose(rotation_from_ypr_deg(80.0, 0.0, 0.0))
    plain = RenderConfig(noise=False, head=False)
    free = render(MODEL, scene.camera, T, plain).visible_fraction
    # The default head sits inside the cap: it never covers a front-facing face here.
    default = render(MODEL, scene.camera, T, RenderConfig(noise=False)).visible_fraction
    assert all(default[k] >= free[k] - 0.02 for k in free)
    # A bigger head (thick hair poking past the cap rim) hides faces through the depth test.
    big = RenderConfig(noise=False, head_centre_m=(0.0, 0.0, -0.03),
                       head_semi_axes_m=(0.12, 0.1, 0.13))
    frame = render(MODEL, scene.camera, T, big)
    hidden = [k for k in free if free[k] > 0.5 and frame.visible_fraction[k] < 0.2]
    assert hidden
    assert not set(hidden) & set(detect(frame.image))
