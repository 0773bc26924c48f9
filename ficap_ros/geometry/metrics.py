"""Rotation metrics, head angles and robust rotation averaging.

Two error measures between orientations, both in degrees:
    ``phi3_deg`` = arccos(|q1 . q2|), Huynh's Phi3, the paper's metric (Table 1, Table 2). It is
        *half* the angle of the rotation that takes one orientation to the other.
    ``angle_deg`` = 2 * Phi3, the geodesic angle (the angle of R1^T R2). Our own thresholds use it.

Corner errors (``corner_errors_px``) of detected tag corners against the true ones, pixels: the
distance, and the *radial offset* (the error's component along the tag centre -> corner direction;
negative = the corner sits inside the tag, the signature of a tone-curve bias).

Head angles (``yaw_pitch_roll_deg``) of a head frame H (x forward, y left, z up) in a reference
frame with the same axes at zero pose, REP-103: right-hand rotations, R = Rz(yaw) Ry(pitch) Rx(roll)
(intrinsic z-y'-x''), the same numbers as tf2's ``getRPY`` / ``getEulerYPR``:
    yaw: positive turning to the wearer's left (right-hand about +z, up);
    pitch: positive nose DOWN (right-hand about +y, which points left: a look down at the instrument
        cluster is positive, a glance up at the rear-view mirror negative);
    roll: positive tilting the head toward the right shoulder (right-hand about +x, forward).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.errors import CalibrationError

__all__ = [
    "phi3_deg",
    "angle_deg",
    "yaw_pitch_roll_deg",
    "rotation_from_ypr_deg",
    "robust_mean_rotation",
    "summarize_errors",
    "corner_errors_px",
]


def phi3_deg(r1: Rotation, r2: Rotation) -> np.ndarray | float:
    """Huynh's Phi3 = arccos(|q1 . q2|) in degrees (half the geodesic angle).

    Works element-wise on stacked rotations.
    """
    q1 = r1.as_quat()
    q2 = r2.as_quat()
    dot = np.abs(np.sum(q1 * q2, axis=-1))
    out = np.degrees(np.arccos(np.clip(dot, 0.0, 1.0)))
    return float(out) if np.ndim(out) == 0 else out


def angle_deg(r1: Rotation, r2: Rotation) -> np.ndarray | float:
    """Geodesic angle between two orientations, degrees (= 2 * Phi3); element-wise."""
    out = np.degrees((r1.inv() * r2).magnitude())
    return float(out) if np.ndim(out) == 0 else out


def yaw_pitch_roll_deg(rotation: Rotation) -> np.ndarray:
    """(yaw, pitch, roll) in degrees of a head rotation (convention in the module docstring).

    Returns shape (3,) for one rotation, (N, 3) for stacked ones.
    """
    return np.array(rotation.as_euler("ZYX", degrees=True), dtype=np.float64)


def yaw_pitch_roll_rad(rotation: Rotation) -> np.ndarray:
    """``yaw_pitch_roll_deg`` in radians (the same convention)."""
    return np.array(rotation.as_euler("ZYX"), dtype=np.float64)


def rotation_from_ypr_deg(yaw_deg: float, pitch_deg: float, roll_deg: float) -> Rotation:
    """Inverse of ``yaw_pitch_roll_deg`` for one rotation (REP-103: pitch positive nose down)."""
    return Rotation.from_euler("ZYX", [yaw_deg, pitch_deg, roll_deg], degrees=True)


def robust_mean_rotation(
    rotations: Rotation, max_iterations: int = 10, cutoff_sigmas: float = 3.0,
    min_cutoff_deg: float = 0.5,
) -> tuple[Rotation, np.ndarray]:
    """Robust average of rotations: chordal mean with iterative outlier rejection.

    The chordal L2 mean (``Rotation.mean``) is recomputed over the rotations whose geodesic
    distance to it is within ``max(cutoff_sigmas * 1.4826 * MAD, min_cutoff_deg)`` of the median
    distance, until the inlier set stops changing.

    Returns:
        (mean rotation, boolean inlier mask).
    Raises:
        CalibrationError: no rotations.
    """
    n = len(rotations) if not rotations.single else 1
    if n == 0:
        raise CalibrationError("no rotations to average")
    if rotations.single:
        return rotations, np.ones(1, dtype=bool)
    inliers = np.ones(n, dtype=bool)
    mean = rotations.mean()
    for _ in range(max_iterations):
        dist = np.degrees((mean.inv() * rotations).magnitude())
        med = float(np.median(dist[inliers]))
        mad = float(np.median(np.abs(dist[inliers] - med)))
        cutoff = med + max(cutoff_sigmas * 1.4826 * mad, min_cutoff_deg)
        new_inliers = dist <= cutoff
        if not np.any(new_inliers):
            break
        mean = rotations[new_inliers].mean()
        if np.array_equal(new_inliers, inliers):
            break
        inliers = new_inliers
    return mean, inliers


def summarize_errors(errors_deg: np.ndarray) -> dict[str, float]:
    """Mean, median and 95th percentile of an error series, degrees (NaNs ignored)."""
    e = np.asarray(errors_deg, dtype=np.float64)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"n": 0, "mean": float("nan"), "median": float("nan"), "p95": float("nan"),
                "max": float("nan")}
    return {
        "n": int(e.size),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "p95": float(np.percentile(e, 95)),
        "max": float(np.max(e)),
    }


def corner_errors_px(corners_px: np.ndarray, true_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-corner error of tag corners against the truth.

    Args:
        corners_px: (N, 4, 2) estimated corners.
        true_px: (N, 4, 2) true corners, same order.

    Returns:
        (error_px, radial_px), each (N, 4): the distance, and the signed component along the
        direction from the true tag centre to the true corner (negative = inward).
    """
    est = np.asarray(corners_px, dtype=np.float64).reshape(-1, 4, 2)
    true = np.asarray(true_px, dtype=np.float64).reshape(-1, 4, 2)
    diff = est - true
    out = true - true.mean(axis=1, keepdims=True)
    out /= np.maximum(np.linalg.norm(out, axis=2, keepdims=True), 1e-12)
    return np.linalg.norm(diff, axis=2), np.einsum("nkd,nkd->nk", diff, out)
