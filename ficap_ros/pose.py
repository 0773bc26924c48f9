"""Rigid cap pose from the detected tag corners.

(API contract; implementation in progress.)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ficap_ros.camera import CameraModel
from ficap_ros.cap_model import CapModel
from ficap_ros.detection import TagDetection
from ficap_ros.transform import Transform

__all__ = ["PoseConfig", "CapPose", "PoseResult", "estimate_cap_pose", "POSE_METHODS"]

POSE_METHODS = ("joint", "paper")


@dataclass(frozen=True)
class PoseConfig:
    method: str = "joint"
    min_tags: int = 1


@dataclass(frozen=True)
class CapPose:
    """A cap pose.

    Attributes:
        T_cam_cap: pose of the cap frame C in the camera optical frame (translation in metres).
        tags_detected: model tags detected in the frame (after duplicate resolution).
        tags_used: tags kept by the estimator.
        used_ids: their ids, sorted.
        rms_px: RMS reprojection error of the used corners, px.
        covariance: 6x6, ROS order (x, y, z in m; rotation about the camera's x, y, z in rad), of a
            small perturbation T = (exp(d_theta) R, t + d_t) of ``T_cam_cap``.
        reliability: score in [0, 1] (mapping in ``reliability_score``).
        method: the estimator's name.
    """

    T_cam_cap: Transform
    tags_detected: int
    tags_used: int
    used_ids: tuple[int, ...]
    rms_px: float
    covariance: np.ndarray
    reliability: float
    method: str


@dataclass(frozen=True)
class PoseResult:
    """An estimator's answer for one frame: a pose, or none with the reason."""

    pose: CapPose | None
    tags_detected: int
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.pose is not None


def estimate_cap_pose(
    detections: Sequence[TagDetection],
    model: CapModel,
    camera: CameraModel,
    config: PoseConfig | None = None,
) -> PoseResult:
    raise NotImplementedError
