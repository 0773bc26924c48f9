"""Frames of a cap turning in front of a camera, with exact truth: the as-built model's tests
(test/tools/model_build, test/cli/test_model_build.py) build from them and measure against it."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel, nominal_model
from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.tools.model_build import align_model
from ficap_ros.vision.detector import TagDetection

CAMERA = CameraModel.pinhole(1280, 960, hfov_deg=60.0)


def perturbed_model(seed: int, shift_rms_mm: float = 0.5, turn_sigma_deg: float = 1.0) -> CapModel:
    """The nominal cap with every tag shifted (``shift_rms_mm`` rms) and turned about its normal.

    The result is aligned to the nominal (the unobservable rigid motion of the whole cap removed),
    so it can be compared with a built model directly.
    """
    rng = np.random.default_rng(seed)
    nom = nominal_model()
    corners = []
    for c, centre, normal in zip(nom.corners_mm, nom.centres_mm, nom.normals):
        turn = Rotation.from_rotvec(normal * np.radians(rng.normal(0.0, turn_sigma_deg)))
        shift = rng.normal(0.0, shift_rms_mm / np.sqrt(3.0), 3)
        corners.append(turn.apply(c - centre) + centre + shift)
    corners = np.array(corners)
    return CapModel(nom.ids, align_model(corners, nom.corners_mm).apply(corners))


def observe(model: CapModel, count: int, seed: int, noise_px: float = 0.15,
            camera: CameraModel = CAMERA) -> list[tuple[Transform, list[TagDetection]]]:
    """Frames of a cap turning in front of a rear camera: exact projections plus pixel noise.

    A tag is seen when it faces the camera (more than ~20 deg from edge-on) and lies in the image.
    """
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(count):
        yaw, pitch, roll = rng.uniform([-45.0, -25.0, -20.0], [45.0, 25.0, 20.0])
        rotation = CAM_FROM_FORWARD * rotation_from_ypr_deg(yaw, pitch, roll)
        t_m = np.array([rng.uniform(-0.04, 0.04), rng.uniform(-0.04, 0.04), rng.uniform(0.45, 0.7)])
        T = Transform(rotation, t_m)
        dets = []
        for tag_id, corners, centre, normal in zip(model.ids, model.corners_mm, model.centres_mm,
                                                   model.normals):
            c_cam = T.apply(centre / 1000.0)
            if np.dot(rotation.apply(normal), c_cam / np.linalg.norm(c_cam)) > -0.35:
                continue
            px = camera.project(T.apply(corners / 1000.0))
            if np.any(px < 0) or np.any(px >= [camera.width_px - 1, camera.height_px - 1]):
                continue
            dets.append(TagDetection(tag_id, px + rng.normal(0.0, noise_px, px.shape)))
        frames.append((T, dets))
    return frames


def corner_rms_mm(a: CapModel, b: CapModel) -> float:
    d = a.corners_mm - b.corners_mm
    return float(np.sqrt(np.mean(np.sum(d * d, axis=-1))))


def rigid_rms_mm(a: CapModel, truth: CapModel) -> float:
    """RMS corner distance after the rigid alignment of ``a`` onto the truth."""
    aligned = align_model(a.corners_mm, truth.corners_mm).apply(a.corners_mm.reshape(-1, 3))
    d = aligned - truth.corners_mm.reshape(-1, 3)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=-1))))


def radially_biased(frames: list[tuple[Transform, list[TagDetection]]], radial_px: float) -> list[list[TagDetection]]:
    """Every corner moved ``radial_px`` along its tag's centre -> corner direction in the image
    (negative = inward), the offset ``metrics.corner_errors_px`` measures: not the builder's own
    edge-offset model (on a foreshortened tag the two differ), so the test cannot pass by
    construction."""
    out = []
    for _, dets in frames:
        biased = []
        for d in dets:
            out_dir = d.corners_px - d.corners_px.mean(axis=0)
            out_dir /= np.linalg.norm(out_dir, axis=1, keepdims=True)
            biased.append(TagDetection(d.tag_id, d.corners_px + radial_px * out_dir))
        out.append(biased)
    return out
