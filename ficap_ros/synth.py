"""Rendered Fi-Cap frames with exact ground truth, and naturalistic driving head motion.

(Stub: the API below is the contract; the implementation is being written.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ficap_ros.camera import CameraModel
from ficap_ros.cap_model import CapModel
from ficap_ros.transform import Transform

__all__ = ["RenderConfig", "RenderedFrame", "render"]


@dataclass(frozen=True)
class RenderConfig:
    lighting: str = "neutral"


@dataclass(frozen=True)
class RenderedFrame:
    image: np.ndarray
    T_cam_cap: Transform
    corners_px: dict[int, np.ndarray]


def render(model: CapModel, camera: CameraModel, T_cam_cap: Transform,
           config: RenderConfig | None = None, seed: int = 0) -> RenderedFrame:
    raise NotImplementedError
