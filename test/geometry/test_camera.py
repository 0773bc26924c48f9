"""ficap_ros.geometry.camera.CameraModel identity: one key, equality and hash."""

from __future__ import annotations

import numpy as np

from ficap_ros.geometry.camera import CameraModel


def test_camera_models_compare_and_hash_by_value() -> None:
    a = CameraModel.pinhole(960, 540, f_px=700.0)
    b = CameraModel(960, 540, a.K.copy(), np.zeros(0), "none")
    c = CameraModel(960, 540, a.K * [[1.0001], [1], [1]], np.zeros(0), "none")
    assert a == b and hash(a) == hash(b) and len({a, b}) == 1
    assert a != c and a != "camera"
    d = CameraModel(960, 540, a.K, [0.1, 0, 0, 0, 0], "plumb_bob")
    assert d != a and d.key != a.key


def test_pick_camera_info_nearest_within_tolerance_else_last_before() -> None:
    from ficap_ros.geometry.camera import pick_camera_info

    ms = 1_000_000
    stamps = [100 * ms, 105 * ms, 105 * ms, 120 * ms]
    assert pick_camera_info(stamps, 100 * ms, ms) == 0  # equal stamp
    assert pick_camera_info(stamps, 119 * ms + 500_000, ms) == 3  # 0.5 ms after the image
    assert pick_camera_info(stamps, 110 * ms, ms) == 2  # none close: the last at or before
    assert pick_camera_info(stamps, 105 * ms, ms) == 2  # equal stamps: the last received
    assert pick_camera_info(stamps, 99 * ms, ms) == 0  # 1 ms before the first: within
    assert pick_camera_info(stamps, 50 * ms, ms) == 0  # before every one: the first
    assert pick_camera_info(stamps, 500 * ms, ms) == 3
    assert pick_camera_info([0, 10], 5, 5) == 0  # a tie: the earlier
    assert pick_camera_info([0, 10], 6, 5) == 1  # the nearer
    assert pick_camera_info([0, 10], 6, 0) == 0  # zero tolerance: the last before
