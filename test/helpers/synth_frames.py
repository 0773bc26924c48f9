"""Helpers of the renderer's tests (test/tools/synth): an independent detector (OpenCV's ArUco
with sub-pixel corners), the view angle of each tag, the corner errors of a rendered frame against
its truth, a lone frontal tag and the crossing of a level along a vertical edge."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.cap_model import TAG_SIDE_MM, CapModel, nominal_model
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth import RenderConfig

MODEL = nominal_model()
#: An idealised camera (no lens blur, grey levels proportional to light): what the geometry tests
#: need; the realistic chain's corner bias is measured apart (test/cli/test_synth.py's
#: ``test_naive_peer_is_biased_inward_on_default_synth_frames``).
IDEAL = RenderConfig(psf_sigma_px=0.0, tone="linear")


def detect(image: np.ndarray) -> dict[int, np.ndarray]:
    """Tag id -> (4, 2) corners found by OpenCV's ArUco detector (tag36h11, sub-pixel corners)."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params
    )
    corners, ids, _ = detector.detectMarkers(image)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2).astype(np.float64) for c, i in zip(corners, ids.ravel())}


def view_angles_deg(T_cam_cap: Transform) -> dict[int, float]:
    """Angle between each tag's outward normal and the direction to the camera, deg."""
    normals = T_cam_cap.rotation.apply(MODEL.normals)
    centres = T_cam_cap.apply(MODEL.centres_mm / 1000.0)
    to_cam = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    cos = np.clip(np.einsum("ij,ij->i", normals, to_cam), -1.0, 1.0)
    return {tag_id: float(np.degrees(np.arccos(c))) for tag_id, c in zip(MODEL.ids, cos)}


def corner_errors(frame, max_view_deg: float = 60.0) -> tuple[np.ndarray, list[int], list[int]]:  # noqa: ANN001
    """Signed corner errors (n, 2) of well-seen tags, their ids missed, and ids wrongly detected."""
    found = detect(frame.image)
    angles = view_angles_deg(frame.T_cam_cap)
    wanted = [k for k, v in frame.visible_fraction.items() if v >= 0.99 and angles[k] < max_view_deg]
    wrong = [k for k in found if k not in frame.corners_px]
    missing = [k for k in wanted if k not in found]
    errors = np.concatenate([found[k] - frame.corners_px[k] for k in wanted if k in found])
    return errors, missing, wrong


def frontal_square(z_m: float) -> tuple[CapModel, Transform]:
    """One 32 mm tag facing the camera squarely at depth ``z_m``, left edge off the pixel grid."""
    h = TAG_SIDE_MM / 2
    corners = np.array([[[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]]])
    return CapModel((0,), corners), Transform(Rotation.identity(), np.array([0.0013, 0.0, z_m]))


def edge_crossing_px(image: np.ndarray, x_edge: float, rows: slice, level: float) -> float:
    """Mean x (OpenCV pixel convention) where rows go from above ``level`` (white quiet zone, left)
    to below it (black border), searched near ``x_edge``."""
    xs = []
    x0 = int(np.floor(x_edge)) - 8
    for row in image[rows, x0:x0 + 17].astype(np.float64):
        k = int(np.flatnonzero((row[:-1] >= level) & (row[1:] < level))[0])
        xs.append(x0 + k + (row[k] - level) / (row[k] - row[k + 1]))
    return float(np.mean(xs))
