"""Corners of a moving cap as a rolling shutter sees them: each corner where the cap was when its
row was exposed (the row's time depends on where the corner lands, so it is found by iterating)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.detector import TagDetection


def constant_velocity(T0: Transform, twist: np.ndarray) -> Callable[[float], Transform]:
    """The pose at time ``s`` (s from the stamp) of a cap at ``T0`` at the stamp moving at the
    constant ``twist`` (6,: linear m/s of the cap origin, angular rad/s, camera axes)."""
    twist = np.asarray(twist, dtype=float)

    def at(s: float) -> Transform:
        R = Rotation.from_rotvec(twist[3:] * s) * T0.rotation
        return Transform(R, T0.translation_m + twist[:3] * s)

    return at


def accelerating(T0: Transform, twist: np.ndarray, accel: np.ndarray) -> Callable[[float], Transform]:
    """The pose at time ``s`` of a cap at ``T0`` at the stamp moving at ``twist`` there and
    speeding up at the constant ``accel`` (6,: m/s^2 of the cap origin, rad/s^2; camera axes):
    turned by ``exp(w s + alpha s^2 / 2)`` and shifted by ``v s + a s^2 / 2``."""
    twist, accel = np.asarray(twist, dtype=float), np.asarray(accel, dtype=float)

    def at(s: float) -> Transform:
        R = Rotation.from_rotvec(twist[3:] * s + 0.5 * accel[3:] * s * s) * T0.rotation
        return Transform(R, T0.translation_m + twist[:3] * s + 0.5 * accel[:3] * s * s)

    return at


def facing_ids(model: CapModel, T: Transform, min_cos: float = 0.2) -> list[int]:
    """The model's tags facing the camera at ``T`` (cosine of the view angle above ``min_cos``)."""
    n = T.rotation.apply(model.normals)
    c = T.apply(model.centres_mm / 1000.0)
    facing = np.sum(n * c, axis=1) < -min_cos * np.linalg.norm(c, axis=1)
    return [int(i) for i in np.asarray(model.ids)[facing]]


def rolling_corners(model: CapModel, camera: CameraModel, pose_at: Callable[[float], Transform],
                    timing: CameraTiming, tag_ids: list[int], iterations: int = 8) -> dict[int, np.ndarray]:
    """Per tag, its four corners (4, 2) in the (distorted) image, each projected from the pose at
    its row's time (``timing.row_time_s``)."""
    out = {}
    for tag_id in tag_ids:
        corners_m = model.corners_of(tag_id) / 1000.0
        px = camera.project(pose_at(0.0).apply(corners_m))
        for _ in range(iterations):
            times = timing.row_time_s(px[:, 1], camera.height_px)
            px = np.stack([camera.project(pose_at(float(t)).apply(c[None]))[0]
                           for t, c in zip(times, corners_m)])
        out[tag_id] = px
    return out


def detections(corners: dict[int, np.ndarray], rng: np.random.Generator | None = None,
               noise_px: float = 0.0) -> list[TagDetection]:
    """Detections of the corners, with seeded Gaussian noise when ``rng`` is given."""
    return [TagDetection(i, c + (0.0 if rng is None else rng.normal(0.0, noise_px, c.shape)))
            for i, c in corners.items()]


def bag_truths(bag: Path) -> dict[int, tuple[Transform, float]]:
    """A synth bag's truth per stamp, ns: (T_cam_cap at the stamp, the cap's angular speed
    there, deg/s), from its truth topics."""
    from ficap_ros.cli.synth import TRUTH_CAP_TOPIC, TRUTH_TWIST_TOPIC
    from ficap_ros.io.messages import pose_to_transform, twist_to_array
    from ficap_ros.io.sources import open_bag_reader
    from ficap_ros.stamps import stamp_to_ns

    truth: dict[int, dict] = {}
    reader = open_bag_reader(bag)
    try:
        conns = [c for c in reader.connections if c.topic in (TRUTH_CAP_TOPIC, TRUTH_TWIST_TOPIC)]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            truth.setdefault(stamp_to_ns(msg.header.stamp), {})[conn.topic] = msg
    finally:
        reader.close()
    return {stamp: (pose_to_transform(m[TRUTH_CAP_TOPIC]),
                    float(np.degrees(np.linalg.norm(twist_to_array(m[TRUTH_TWIST_TOPIC])[3:]))))
            for stamp, m in truth.items()}
