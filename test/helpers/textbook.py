"""Checks independent of ficap_ros.geometry and of scipy: what a test compares the package with."""

from __future__ import annotations

import numpy as np


def pose_matrix(q_xyzw: tuple[float, float, float, float],
                t: tuple[float, float, float]) -> np.ndarray:
    """4x4 homogeneous matrix of a unit quaternion (x, y, z, w order, as ROS messages carry it)
    and a translation, by the textbook formula."""
    x, y, z, w = q_xyzw
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = t
    return m
