"""ficap_ros.camera.CameraModel identity: one key, equality and hash."""

from __future__ import annotations

import numpy as np

from ficap_ros.camera import CameraModel


def test_camera_models_compare_and_hash_by_value() -> None:
    a = CameraModel.pinhole(960, 540, f_px=700.0)
    b = CameraModel(960, 540, a.K.copy(), np.zeros(0), "none")
    c = CameraModel(960, 540, a.K * [[1.0001], [1], [1]], np.zeros(0), "none")
    assert a == b and hash(a) == hash(b) and len({a, b}) == 1
    assert a != c and a != "camera"
    d = CameraModel(960, 540, a.K, [0.1, 0, 0, 0, 0], "plumb_bob")
    assert d != a and d.key != a.key
