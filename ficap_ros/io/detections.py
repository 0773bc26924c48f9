"""Per-tag detections of a frame: each detected tag's corners, whether the cap pose used it and its
residual against that pose (``TagFits``, a frame record's ``tags``); published by the node and
written by ``ficap replay`` in three forms:

- ``apriltag_msgs/AprilTagDetectionArray`` (``apriltag_array``): what christianrauch/apriltag_ros
  publishes, in its conventions: family ``tag36h11``, corners in AprilTag's order and pixel
  convention (p0..p3 at tag coordinates (-1, 1), (1, 1), (1, -1), (-1, -1); (0, 0) the outer
  corner of the top-left pixel), ``homography`` mapping tag coordinates to those pixels
  (row-major, H[2][2] = 1), ``centre`` its image of (0, 0), ``goodness`` 0 (AprilTag 3 has none),
  ``decision_margin`` NaN where the detector does not say (OpenCV's).
- named numbers (``fit_values``, a ``sensor_msgs/JointState`` by ``messages.named_values``):
  ``tag<id>/used`` (1 or 0) and ``tag<id>/residual_px`` per detected tag, which a plotter reads
  by name.
- detections.csv rows (``detections_csv_text``), corners in the project's convention (OpenCV's
  order c0..c3 and pixel centres, as ``ficap detect`` prints them).

Residuals are RMS over the tag's four corners of the distance, px, between the detected corners
and the cap model's corners projected through the frame's cap pose and the camera (lens
distortion included: the detected image's pixels); NaN without a pose. No rclpy here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterable, Sequence

import numpy as np

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.io import messages
from ficap_ros.vision.detector import TagDetection
from ficap_ros.vision.pose import CapPose

if TYPE_CHECKING:
    from ficap_ros.io.labels import FrameRecord

__all__ = ["TagFits", "tag_fits", "apriltag_corners", "apriltag_homographies", "apriltag_array", "fit_values",
           "DETECTION_COLUMNS", "detections_csv_text", "TAG_FAMILY"]

TAG_FAMILY = "tag36h11"
#: OpenCV's corner c_i is AprilTag's p_ORDER[i] and the reverse (the order is its own inverse).
_APRILTAG_ORDER = (1, 0, 3, 2)
#: AprilTag's pixel convention minus OpenCV's, px.
_APRILTAG_OFFSET_PX = 0.5
#: AprilTag's tag coordinates of p0..p3.
_TAG_XY = np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]])


@dataclass(frozen=True)
class TagFits:
    """The tags detected in one frame (arrays: compact over a whole recording's records).

    Attributes:
        ids: (N,) tag ids, in detection order (a duplicate id appears twice).
        corners_px: (N, 4, 2) detected corners, OpenCV order and pixel convention, image px.
        used: (N,) whether the cap pose used the tag.
        residual_px: (N,) RMS corner residual against the cap pose, px (NaN without a pose).
        hamming: (N,) bits corrected while decoding.
        decision_margin: (N,) the detector's decoding margin (NaN where it does not say).
    """

    ids: np.ndarray
    corners_px: np.ndarray
    used: np.ndarray
    residual_px: np.ndarray
    hamming: np.ndarray
    decision_margin: np.ndarray

    def __len__(self) -> int:
        return int(self.ids.size)


def tag_fits(detections: Sequence[TagDetection], pose: CapPose | None, model: CapModel,
             camera: CameraModel) -> TagFits:
    """Each detection with its use and residual under ``pose`` (module docstring)."""
    n = len(detections)
    corners = np.array([d.corners_px for d in detections], dtype=np.float64).reshape(n, 4, 2)
    ids = np.array([d.tag_id for d in detections], dtype=np.int64)
    residual = np.full(n, math.nan)
    used = np.zeros(n, dtype=bool)
    if pose is not None and n:
        used_ids = set(pose.used_ids)  # a few dozen ids: a set beats np.isin's sorting
        used = np.array([i in used_ids for i in ids.tolist()], dtype=bool)
        model_m = model.corners_mm[[model.index_of(i) for i in ids.tolist()]] / 1000.0
        projected = camera.project(pose.T_cam_cap.apply(model_m.reshape(-1, 3))).reshape(n, 4, 2)
        residual = np.sqrt(np.mean(np.sum((projected - corners) ** 2, axis=-1), axis=-1))
    return TagFits(ids, corners, used, residual,
                   np.array([d.hamming for d in detections], dtype=np.int64),
                   np.array([d.decision_margin for d in detections], dtype=np.float64))


def apriltag_corners(corners_px: np.ndarray) -> np.ndarray:
    """OpenCV-order corners (4, 2) in OpenCV's pixel convention -> AprilTag's p0..p3 in its own."""
    return np.asarray(corners_px, dtype=np.float64)[list(_APRILTAG_ORDER)] + _APRILTAG_OFFSET_PX


def _homographies(p: np.ndarray) -> np.ndarray:
    """Tag coordinates -> AprilTag pixels, (N, 3, 3) with H[2][2] = 1, from each tag's p0..p3
    (N, 4, 2): the four correspondences' 8x8 linear system, solved for all tags at once."""
    n = len(p)
    A = np.zeros((n, 8, 8))
    x, y = _TAG_XY[:, 0], _TAG_XY[:, 1]
    u, v = p[:, :, 0], p[:, :, 1]
    A[:, 0::2, 0], A[:, 0::2, 1], A[:, 0::2, 2] = x, y, 1.0
    A[:, 1::2, 3], A[:, 1::2, 4], A[:, 1::2, 5] = x, y, 1.0
    A[:, 0::2, 6], A[:, 0::2, 7] = -u * x, -u * y
    A[:, 1::2, 6], A[:, 1::2, 7] = -v * x, -v * y
    h = np.linalg.solve(A, p.reshape(n, 8)[..., None])[..., 0]
    return np.concatenate([h, np.ones((n, 1))], axis=1).reshape(n, 3, 3)


def apriltag_homographies(frames: Sequence[TagFits]) -> list[np.ndarray]:
    """Each frame's ``apriltag_array`` homographies, (N_i, 3, 3) per frame, from one solve over
    every frame's tags: each tag's system is solved on its own, so the values are a frame's own
    to the bit, without the solve's fixed cost per frame."""
    p = np.concatenate([np.zeros((0, 4, 2))] + [f.corners_px[:, list(_APRILTAG_ORDER)] for f in frames])
    H = _homographies(p + _APRILTAG_OFFSET_PX) if len(p) else np.zeros((0, 3, 3))
    return np.split(H, np.cumsum([len(f) for f in frames])[:-1]) if frames else []


def apriltag_array(c: messages.MessageClasses, head: Any, fits: TagFits,
                   homographies: np.ndarray | None = None) -> Any:
    """``apriltag_msgs/AprilTagDetectionArray`` of a frame's detections (module docstring);
    ``homographies``: theirs (``apriltag_homographies``), solved here when not given."""
    point, detection = c.types["apriltag_msgs/msg/Point"], c.types["apriltag_msgs/msg/AprilTagDetection"]
    p = fits.corners_px[:, list(_APRILTAG_ORDER)] + _APRILTAG_OFFSET_PX  # apriltag_corners, each
    if homographies is not None:
        H = homographies
    else:
        H = _homographies(p) if len(fits) else np.zeros((0, 3, 3))
    # Python scalars once per array (tolist), not a numpy scalar per field; the homographies'
    # field values once for all tags (``c.floats``), each tag's nine a slice of them.
    flat = c.floats(H)
    rows = zip(fits.ids.tolist(), fits.hamming.tolist(), fits.decision_margin.tolist(),
               p.tolist(), H[:, 0, 2].tolist(), H[:, 1, 2].tolist(), range(0, 9 * len(H), 9))
    out = [detection(family=TAG_FAMILY, id=int(tag_id), hamming=int(hamming), goodness=0.0,
                     decision_margin=float(margin),
                     centre=point(x=cx, y=cy),  # H (0, 0, 1); H[2][2] = 1
                     corners=[point(x=x, y=y) for x, y in corners],
                     homography=flat[k:k + 9])
           for tag_id, hamming, margin, corners, cx, cy, k in rows]
    return c.types["apriltag_msgs/msg/AprilTagDetectionArray"](header=head, detections=out)


def fit_values(fits: TagFits) -> dict[str, float]:
    """``tag<id>/used`` (1 or 0) and ``tag<id>/residual_px`` of every detected tag, in detection
    order."""
    out: dict[str, float] = {}
    for tag_id, used, residual in zip(fits.ids.tolist(), fits.used.tolist(), fits.residual_px.tolist()):
        out[f"tag{tag_id}/used"] = 1.0 if used else 0.0
        out[f"tag{tag_id}/residual_px"] = residual
    return out


#: detections.csv's columns: a row per detected tag of every frame.
DETECTION_COLUMNS: tuple[str, ...] = (
    "frame", "stamp_ns", "tag_id", "used", "residual_px", "hamming", "decision_margin",
    *(f"c{i}_{a}_px" for i in range(4) for a in "xy"),
)


def _num(value: float, digits: int) -> str:
    return f"{value:.{digits}f}" if math.isfinite(value) else ""


#: Eight finite corner coordinates, as ``_num`` writes each.
_CORNERS_FORMAT = ",".join(["{:.4f}"] * 8)


def _corners_text(corners: list[float]) -> str:
    """One row's eight corner fields (c0_x .. c3_y), ``_num``'s text for each."""
    if all(map(math.isfinite, corners)):
        return _CORNERS_FORMAT.format(*corners)
    return ",".join([_num(v, 4) for v in corners])


def detections_csv_text(records: Iterable[FrameRecord]) -> str:
    """detections.csv: a header row and a row per detected tag of every record (corners and
    residuals to 4 decimals, px; empty where NaN).

    Every field is a number or empty, so rows are joined directly (what ``csv.writer`` writes for
    them, without its per-field work); each array becomes Python scalars once (``tolist``).
    """
    lines = [",".join(DETECTION_COLUMNS)]
    for rec in records:
        fits = rec.tags
        if fits is None or not len(fits):
            continue
        lead = f"{int(rec.index)},{int(rec.stamp_ns)},"
        rows = zip(fits.ids.tolist(), fits.used.tolist(), fits.residual_px.tolist(),
                   fits.hamming.tolist(), fits.decision_margin.tolist(),
                   fits.corners_px.reshape(len(fits), 8).tolist())
        lines += [f"{lead}{int(tag_id)},{int(used)},{_num(residual, 4)},{int(hamming)},"
                  f"{_num(margin, 4)},{_corners_text(corners)}"
                  for tag_id, used, residual, hamming, margin, corners in rows]
    return "\n".join(lines) + "\n"
