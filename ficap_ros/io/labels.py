"""Head-pose labels: one record per image (``FrameRecord``, the node's and the bag tools' alike,
where the head pose is composed from the cap pose), written as CSV and as a rosbag2 MCAP; read back.

Frames and quaternions (CSV columns are w, x, y, z; ROS messages store x, y, z, w):
    cap_q*, cap_*_m: T_cam_cap, the cap frame C in the camera optical frame (m).
    head_q*, head_*_deg: R_frontal_head, the head frame H in the frontal frame F (the head's zero
        pose); yaw/pitch/roll as in ``ficap_ros.geometry.metrics``: REP-103 (right-hand, intrinsic ZYX, as
        tf2's getRPY), pitch positive nose DOWN. Identity-mounted (R_cap_head = I) until a
        calibration is given (column ``calibrated``).
    rot_err95_deg, trans_err95_mm: predicted 95 % bounds of this frame's cap pose error, the
        geodesic rotation angle (deg) and the translation length (mm), from the covariance
        (``ficap_ros.vision.pose``: residuals, corner bias, cap model, intrinsics); ``reliability`` is
        derived from rot_err95_deg. They do not include the head calibration's own uncertainty.
    head_v*_m_s, head_w*_rad_s (the last six columns): the head's twist at the stamp in the
        frontal frame F's axes (the velocity of the head origin, which is the cap origin, in m/s;
        its angular velocity in rad/s, ``R(t + dt) = exp([w] dt) R(t)``); empty (NaN) where the
        pose estimator does not measure it (``CapPose.velocity`` None) or there is no pose.

labels.mcap holds the live node's topics (``ficap_ros.ros.node``), with the same messages, each stamped
with the image stamp (header and bag receive time); names relative to ``namespace`` (default none:
``/head_pose`` ...). The poses are in the frames ``ficap_ros.io.frames.OutputFrames`` says, as the
node's: by default the camera's (the image's frame_id) and the frontal frame ``ficap_frontal``:
    ``head_pose`` PoseStamped: T_cam_head = T_cam_cap * R_cap_head (camera optical frame; in
        ``output_frame`` through ``camera_mount`` when one is given).
    ``head_pose/with_covariance`` PoseWithCovarianceStamped: the same with the estimator's 6x6
        covariance (ROS order, m and rad, the pose's frame).
    ``cap_pose`` PoseStamped: T_cam_cap (the same frame).
    ``head_pose/frontal`` PoseStamped: the head in the frontal frame F.
    ``head_rpy_deg`` Vector3Stamped: x roll, y pitch, z yaw of H in F, degrees (REP-103);
        ``head_rpy`` the same in radians.
    ``quality`` JointState: ``name[i]`` labels ``position[i]`` (``ficap_ros.io.status.quality_values``:
        tag counts, reliability, rms_px, the 95 % bounds in deg and mm and in rad and m; NaN without
        a pose); every image.
    ``status`` DiagnosticArray, one status ``ficap`` per image, level and message as the node's
        (``ficap_ros.io.status.record_status``): OK with a pose, WARN without one or below reliability
        0.5, ERROR for an undecodable image; values tags_detected, tags_used, rms_px, reliability,
        calibrated and, with a pose, yaw_deg, pitch_deg, roll_deg (R_frontal_head).
    ``detections`` apriltag_msgs/AprilTagDetectionArray and ``detections/fit`` JointState
        (``ficap_ros.io.detections``): every decoded image's detected tags, their corners, use and
        residual.
    ``head_twist`` TwistStamped: the head's twist (the cap origin's linear velocity and the
        angular velocity, m/s and rad/s, in the pose outputs' frame), for images whose pose has one.
    ``/tf`` and ``/tf_static`` (never namespaced) tf2_msgs/TFMessage: the TF tree of
        ``ficap_ros.io.frames`` (camera -> ``ficap_cap`` -> ``ficap_head`` per posed image; the
        mount on ``/tf_static``), so a 3-D view (Foxglove, RViz) shows the head moving.
Poses exist in the bag only for images with a pose; status and quality for every image.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.errors import BagError
from ficap_ros.geometry.metrics import yaw_pitch_roll_deg
from ficap_ros.geometry.transform import Transform, inverse, rotate_twist
from ficap_ros.io.detections import TagFits
from ficap_ros.io.frames import CAP_FRAME, FRONTAL_FRAME, HEAD_FRAME, OutputFrames
from ficap_ros.io.status import (
    FrameStatus,
    quality_values,
    record_status,
    status_reason,
    status_values,
)
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.pipeline import FrameResult
from ficap_ros.vision.pose import CapPose

__all__ = [
    "LABEL_COLUMNS",
    "TWIST_COLUMNS",
    "DEFAULT_NAMESPACE",
    "DEFAULT_CAMERA_FRAME",
    "UNCALIBRATED",
    "HeadPose",
    "head_pose",
    "FrameRecord",
    "Labels",
    "labels_csv_text",
    "read_labels",
    "read_labels_text",
    "write_labels_bag",
    "label_topics",
    "FRONTAL_FRAME",
    "CAP_FRAME",
    "HEAD_FRAME",
]

#: The head twist's CSV columns (the last six): linear velocity, then angular velocity, in F.
TWIST_COLUMNS: tuple[str, ...] = (
    "head_vx_m_s", "head_vy_m_s", "head_vz_m_s", "head_wx_rad_s", "head_wy_rad_s", "head_wz_rad_s")
#: CSV columns, in order.
LABEL_COLUMNS: tuple[str, ...] = (
    "frame", "stamp_ns", "tags_detected", "tags_used", "rms_px", "reliability",
    "rot_err95_deg", "trans_err95_mm",
    "cap_qw", "cap_qx", "cap_qy", "cap_qz", "cap_x_m", "cap_y_m", "cap_z_m",
    "head_qw", "head_qx", "head_qy", "head_qz", "head_yaw_deg", "head_pitch_deg", "head_roll_deg",
    "calibrated", "method", "detected_ids", "used_ids", "reason",
    *TWIST_COLUMNS,
)
DEFAULT_NAMESPACE = ""
#: frame_id of labels whose images carry none.
DEFAULT_CAMERA_FRAME = "camera_optical_frame"
#: The head calibration of a record made without one: the cap is the head, the camera looks ahead.
UNCALIBRATED = HeadCalibration()


@dataclass(frozen=True)
class HeadPose:
    """The head pose of one frame.

    Attributes:
        T_cam_head: the head frame H in the camera optical frame (origin at the cap origin).
        T_frontal_head: H in the frontal frame F: rotation R_frontal_head (the head angles),
            translation the cap origin in F's axes at the camera.
    """

    T_cam_head: Transform
    T_frontal_head: Transform


def head_pose(T_cam_cap: Transform, calibration: HeadCalibration) -> HeadPose:
    """The head pose of a cap pose under a head calibration: the one place it is composed.

    The cap pose turned by ``R_cap_head`` (head origin = cap origin) is put in the frontal frame
    (``T_frontal_head``); ``T_cam_head`` is that pose seen from the camera again, so the node's
    ``head_pose``, labels.mcap's and the head angles are one pose to the last bit.
    """
    R_frontal_cam = calibration.R_cam_frontal.inv()
    turned = T_cam_cap * Transform(calibration.R_cap_head, np.zeros(3))
    T_frontal_head = Transform(R_frontal_cam, np.zeros(3)) * turned
    return HeadPose(Transform(inverse(R_frontal_cam), np.zeros(3)) * T_frontal_head, T_frontal_head)


@dataclass(frozen=True)
class FrameRecord:
    """Everything a frame reports: the label of labels.csv / labels.mcap, the node's outputs.

    Attributes:
        index: image index in the recording (0 live).
        stamp_ns: image stamp, ns.
        frame_id: the image's optical frame.
        status: what became of the frame (``FrameStatus``: a pose, no pose, undecodable, failed).
        reason: why there is no pose or the image could not be processed ('' with a pose).
        detected_ids: ids of the model tags detected, sorted, each once.
        pose: the cap pose, or None.
        calibration: the head calibration the head pose is composed with (``head``).
        method: the pose method of the settings.
        tags: the detected tags with their corners, use and residual (None: not kept, or the
            image could not be processed).
    """

    index: int
    stamp_ns: int
    frame_id: str
    status: FrameStatus
    reason: str = ""
    detected_ids: tuple[int, ...] = ()
    pose: CapPose | None = None
    calibration: HeadCalibration = UNCALIBRATED
    method: str = ""
    tags: TagFits | None = None

    @classmethod
    def processed(cls, index: int, stamp_ns: int, frame_id: str, pose: CapPose | None,
                  detected_ids: Iterable[int], reason: str = "",
                  calibration: HeadCalibration = UNCALIBRATED, method: str = "",
                  tags: TagFits | None = None) -> FrameRecord:
        """A processed frame: ``POSE`` with a pose, else ``NO_POSE`` (reason default "no pose");
        ``frame_id`` '' is ``DEFAULT_CAMERA_FRAME``."""
        return cls(int(index), int(stamp_ns), frame_id or DEFAULT_CAMERA_FRAME,
                   FrameStatus.POSE if pose is not None else FrameStatus.NO_POSE,
                   "" if pose is not None else reason or "no pose",
                   tuple(sorted({int(i) for i in detected_ids})), pose, calibration,
                   pose.method if pose is not None else method, tags)

    @classmethod
    def of(cls, result: FrameResult, index: int, stamp_ns: int, frame_id: str,
           calibration: HeadCalibration = UNCALIBRATED, method: str = "",
           tags: TagFits | None = None) -> FrameRecord:
        """The record of the pipeline's result for a frame (``tags``: its detections'
        ``ficap_ros.io.detections.tag_fits``, when kept)."""
        return cls.processed(index, stamp_ns, frame_id, result.pose, result.detected_ids,
                             result.reason, calibration, method, tags)

    @classmethod
    def unprocessed(cls, index: int, stamp_ns: int, frame_id: str, reason: str,
                    status: FrameStatus = FrameStatus.UNDECODABLE,
                    calibration: HeadCalibration = UNCALIBRATED, method: str = "") -> FrameRecord:
        """A frame whose image could not be processed (``UNDECODABLE`` or ``FAILED``)."""
        return cls(int(index), int(stamp_ns), frame_id or DEFAULT_CAMERA_FRAME, status, reason,
                   calibration=calibration, method=method)

    @cached_property
    def head(self) -> HeadPose | None:
        """The head pose (``head_pose`` of the cap pose under ``calibration``), or None."""
        return None if self.pose is None else head_pose(self.pose.T_cam_cap, self.calibration)

    @cached_property
    def head_ypr_deg(self) -> np.ndarray | None:
        """The head angles (yaw, pitch, roll), deg, of ``T_frontal_head`` (``yaw_pitch_roll_deg``;
        read-only, worked out once for labels.csv and the status), or None without a pose."""
        if self.T_frontal_head is None:
            return None
        ypr = yaw_pitch_roll_deg(self.T_frontal_head.rotation)
        ypr.setflags(write=False)
        return ypr

    @property
    def skipped(self) -> bool:
        """The image could not be decoded: a lost frame of the recording."""
        return self.status is FrameStatus.UNDECODABLE

    @property
    def tags_detected(self) -> int:
        return len(self.detected_ids)

    @property
    def tags_used(self) -> int:
        return self.pose.tags_used if self.pose is not None else 0

    @property
    def used_ids(self) -> tuple[int, ...]:
        return tuple(sorted(self.pose.used_ids)) if self.pose is not None else ()

    @property
    def rms_px(self) -> float:
        return float(self.pose.rms_px) if self.pose is not None else math.nan

    @property
    def reliability(self) -> float:
        return float(self.pose.reliability) if self.pose is not None else math.nan

    @property
    def rot_err95_deg(self) -> float:
        """Predicted 95 % bound of the cap pose's geodesic rotation error, deg (NaN: no pose)."""
        return float(self.pose.rot_err95_deg) if self.pose is not None else math.nan

    @property
    def trans_err95_mm(self) -> float:
        """Predicted 95 % bound of the cap pose's translation error, mm (NaN: no pose)."""
        return float(self.pose.trans_err95_mm) if self.pose is not None else math.nan

    @property
    def T_cam_cap(self) -> Transform | None:
        return self.pose.T_cam_cap if self.pose is not None else None

    @property
    def T_cam_head(self) -> Transform | None:
        return self.head.T_cam_head if self.head is not None else None

    @property
    def T_frontal_head(self) -> Transform | None:
        return self.head.T_frontal_head if self.head is not None else None

    @property
    def covariance_cam(self) -> np.ndarray | None:
        """The cap pose's 6x6 covariance (ROS order, camera axes), or None."""
        return None if self.pose is None else np.asarray(self.pose.covariance, dtype=np.float64).reshape(6, 6)

    @property
    def head_twist_cam(self) -> np.ndarray | None:
        """The head's twist at the stamp, (6,) ROS order in the camera's axes, or None when the
        estimator does not measure it: the cap's (``CapPose.velocity``), since the head's origin
        is the cap's and both turn together."""
        if self.pose is None or self.pose.velocity is None:
            return None
        return np.asarray(self.pose.velocity, dtype=np.float64).reshape(6)

    @property
    def head_twist_frontal(self) -> np.ndarray | None:
        """``head_twist_cam`` in the frontal frame F's axes (labels.csv's twist columns)."""
        twist = self.head_twist_cam
        return None if twist is None else rotate_twist(twist, self.R_frontal_cam)

    @property
    def R_frontal_cam(self) -> Rotation:
        """Orientation of the camera in the frontal frame F."""
        return self.calibration.R_cam_frontal.inv()

    @property
    def calibrated(self) -> bool:
        return self.calibration.calibrated


def _f(value: float, digits: int) -> str:
    return "" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _csv_row(rec: FrameRecord) -> list[str]:
    cap = [""] * 7
    head = [""] * 7
    if rec.T_cam_cap is not None and rec.T_frontal_head is not None:
        cap = [_f(v, 9) for v in rec.T_cam_cap.q_wxyz] + [_f(v, 6) for v in rec.T_cam_cap.translation_m]
        head = [_f(v, 9) for v in rec.T_frontal_head.q_wxyz] + [_f(v, 4) for v in rec.head_ypr_deg]
    return [
        str(rec.index), str(rec.stamp_ns), str(rec.tags_detected), str(rec.tags_used),
        _f(rec.rms_px, 4), _f(rec.reliability, 4), _f(rec.rot_err95_deg, 4),
        _f(rec.trans_err95_mm, 3), *cap, *head, "1" if rec.calibrated else "0",
        rec.method, " ".join(map(str, rec.detected_ids)), " ".join(map(str, rec.used_ids)),
        status_reason(rec), *_twist_fields(rec),
    ]


def _twist_fields(rec: FrameRecord) -> list[str]:
    """The twist columns: m/s and rad/s to 6 decimals, empty without a measured twist."""
    twist = rec.head_twist_frontal
    return [""] * 6 if twist is None else [_f(v, 6) for v in twist]


def labels_csv_text(records: Iterable[FrameRecord]) -> str:
    """labels.csv content: a header row and one row per image (pose fields empty without a pose)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(LABEL_COLUMNS)
    for rec in records:
        writer.writerow(_csv_row(rec))
    return buf.getvalue()


@dataclass(frozen=True)
class Labels:
    """labels.csv read back as columns (NaN where a field is empty).

    Attributes:
        stamp_ns: (N,) int64.
        tags_detected, tags_used: (N,) int.
        rms_px, reliability: (N,) float.
        rot_err95_deg, trans_err95_mm: (N,) predicted 95 % error bounds (NaN where absent).
        has_pose: (N,) bool.
        q_cam_cap_wxyz: (N, 4); t_cam_cap_m: (N, 3).
        q_frontal_head_wxyz: (N, 4); head_ypr_deg: (N, 3).
        calibrated: (N,) bool.
        detected_ids: per row, the detected tag ids.
        reasons: per row, why there is no pose ("" with one).
        head_twist: (N, 6) the head's twist in F (m/s, rad/s; ``TWIST_COLUMNS``), NaN where not
            measured (and in files without those columns).
    """

    stamp_ns: np.ndarray
    tags_detected: np.ndarray
    tags_used: np.ndarray
    rms_px: np.ndarray
    reliability: np.ndarray
    has_pose: np.ndarray
    q_cam_cap_wxyz: np.ndarray
    t_cam_cap_m: np.ndarray
    q_frontal_head_wxyz: np.ndarray
    head_ypr_deg: np.ndarray
    calibrated: np.ndarray
    detected_ids: tuple[tuple[int, ...], ...]
    reasons: tuple[str, ...]
    rot_err95_deg: np.ndarray | None = None
    trans_err95_mm: np.ndarray | None = None
    head_twist: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.stamp_ns.size)

    @property
    def skipped(self) -> np.ndarray:
        """(N,) bool: the image could not be decoded (its reason starts ``undecodable``)."""
        return np.array([r.startswith(str(FrameStatus.UNDECODABLE)) for r in self.reasons], dtype=bool)

    def cap_rotations(self) -> Rotation:
        """R_cam_cap of the rows with a pose."""
        return _rot_wxyz(self.q_cam_cap_wxyz[self.has_pose])

    def head_rotations(self) -> Rotation:
        """R_frontal_head of the rows with a pose."""
        return _rot_wxyz(self.q_frontal_head_wxyz[self.has_pose])


def _rot_wxyz(q_wxyz: np.ndarray) -> Rotation:
    q = np.asarray(q_wxyz, dtype=np.float64).reshape(-1, 4)
    return Rotation.from_quat(q[:, [1, 2, 3, 0]])


def _num(text: str) -> float:
    return float(text) if text.strip() else math.nan


def read_labels_text(path: str | Path) -> tuple[Path, str]:
    """The text of a CSV file, or of ``labels.csv`` inside a replay output folder.

    Raises:
        BagError: the file cannot be read.
    """
    from ficap_ros.files import MAX_TABLE_BYTES, read_text

    path = Path(path)
    if path.is_dir():
        path = path / "labels.csv"
    return path, read_text(path, "labels", BagError, MAX_TABLE_BYTES)


def read_labels(path: str | Path) -> Labels:
    """Read labels.csv (or a replay output folder holding one).

    A last row cut short (no final newline, fewer fields) is dropped; any other row whose field
    count differs from the header's is an error.

    Raises:
        BagError: missing file, not UTF-8 text, or not a labels CSV.
    """
    path, text = read_labels_text(path)
    try:
        table = [r for r in csv.reader(io.StringIO(text)) if r]
    except csv.Error as err:
        raise BagError(f"{path} is not a labels CSV: {err}") from err
    columns = table[0] if table else []
    body = table[1:]
    if body and len(body[-1]) != len(columns) and not text.endswith("\n"):
        body.pop()  # a last row cut short (an interrupted copy) is not a frame
    for n, r in enumerate(body):
        if len(r) != len(columns):
            raise BagError(f"{path}: row {n + 2} has {len(r)} fields, the header {len(columns)}")
    rows = [dict(zip(columns, r)) for r in body]
    need = {"stamp_ns", "tags_detected", "cap_qw", "head_qw"}
    header = set(columns)
    if not need <= header:
        raise BagError(f"{path} is not a labels CSV (missing {', '.join(sorted(need - header))})")
    try:
        def col(name: str) -> np.ndarray:
            return np.array([_num(r.get(name) or "") for r in rows], dtype=np.float64)

        stamps = np.array([int(r["stamp_ns"]) for r in rows], dtype=np.int64)
        q_cap = np.stack([col(f"cap_q{a}") for a in "wxyz"], axis=-1).reshape(-1, 4)
        t_cap = np.stack([col(f"cap_{a}_m") for a in "xyz"], axis=-1).reshape(-1, 3)
        q_head = np.stack([col(f"head_q{a}") for a in "wxyz"], axis=-1).reshape(-1, 4)
        ypr = np.stack([col(f"head_{a}_deg") for a in ("yaw", "pitch", "roll")],
                       axis=-1).reshape(-1, 3)
        ids = tuple(tuple(int(v) for v in (r.get("detected_ids") or "").split()) for r in rows)
        return Labels(
            stamp_ns=stamps,
            tags_detected=col("tags_detected").astype(int),
            tags_used=np.nan_to_num(col("tags_used")).astype(int),
            rms_px=col("rms_px"),
            reliability=col("reliability"),
            has_pose=np.all(np.isfinite(q_cap), axis=1) & np.all(np.isfinite(q_head), axis=1),
            q_cam_cap_wxyz=q_cap,
            t_cam_cap_m=t_cap,
            q_frontal_head_wxyz=q_head,
            head_ypr_deg=ypr,
            calibrated=np.array([(r.get("calibrated") or "0").strip() in ("1", "true", "True")
                                 for r in rows], dtype=bool),
            detected_ids=ids,
            reasons=tuple((r.get("reason") or "") for r in rows),
            rot_err95_deg=col("rot_err95_deg"),
            trans_err95_mm=col("trans_err95_mm"),
            head_twist=np.stack([col(c) for c in TWIST_COLUMNS], axis=-1).reshape(-1, 6),
        )
    except (ValueError, KeyError, TypeError) as err:
        raise BagError(f"{path}: malformed labels row: {_first_bad_field(rows) or err}") from err


def _first_bad_field(rows: list[dict[str, str]]) -> str:
    """Where the columns failed to parse, for the error: ``row N, column: 'value'`` (N counts
    the header as row 1, as the field-count check does), or '' when no field is to blame."""
    numbers = {"tags_detected", "tags_used", "rms_px", "reliability", "rot_err95_deg",
               "trans_err95_mm", *(f"{p}_q{a}" for p in ("cap", "head") for a in "wxyz"),
               *(f"cap_{a}_m" for a in "xyz"), *(f"head_{a}_deg" for a in ("yaw", "pitch", "roll")),
               *TWIST_COLUMNS}
    for n, r in enumerate(rows):
        for name, value in r.items():
            try:
                if name in ("stamp_ns", "detected_ids"):
                    [int(v) for v in (value or "").split()]
                elif name in numbers:
                    _num(value or "")
            except ValueError:
                return f"row {n + 2}, {name}: not a number: {value!r}"
    return ""


def label_topics(namespace: str = DEFAULT_NAMESPACE) -> dict[str, str]:
    """Topic name per label stream: cap_pose, head_pose, head_pose_cov, head_frontal, head_rpy
    (degrees), head_rpy_rad, quality, status, detections, detections_fit, head_twist, tf and
    tf_static (``/tf`` and ``/tf_static`` are global, as in ROS: never namespaced)."""
    ns = "/" + namespace.strip("/") if namespace.strip("/") else ""
    return {
        "cap_pose": f"{ns}/cap_pose",
        "head_pose": f"{ns}/head_pose",
        "head_pose_cov": f"{ns}/head_pose/with_covariance",
        "head_frontal": f"{ns}/head_pose/frontal",
        "head_rpy": f"{ns}/head_rpy_deg",
        "head_rpy_rad": f"{ns}/head_rpy",
        "quality": f"{ns}/quality",
        "status": f"{ns}/status",
        "detections": f"{ns}/detections",
        "detections_fit": f"{ns}/detections/fit",
        "tf": "/tf",
        "tf_static": "/tf_static",
        "head_twist": f"{ns}/head_twist",
    }


#: labels.mcap's message type per label stream.
_TOPIC_TYPES = {
    "cap_pose": "geometry_msgs/msg/PoseStamped",
    "head_pose": "geometry_msgs/msg/PoseStamped",
    "head_pose_cov": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "head_frontal": "geometry_msgs/msg/PoseStamped",
    "head_rpy": "geometry_msgs/msg/Vector3Stamped",
    "head_rpy_rad": "geometry_msgs/msg/Vector3Stamped",
    "quality": "sensor_msgs/msg/JointState",
    "status": "diagnostic_msgs/msg/DiagnosticArray",
    "tf": "tf2_msgs/msg/TFMessage",
    "head_twist": "geometry_msgs/msg/TwistStamped",
    "tf_static": "tf2_msgs/msg/TFMessage",
    "detections": "apriltag_msgs/msg/AprilTagDetectionArray",
    "detections_fit": "sensor_msgs/msg/JointState",
}


def _status_text(key: str, value: object) -> str:
    """labels.mcap's status strings: fixed decimals (3 for mm, else 4), '' for NaN."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    return _f(float(value), 3 if key.endswith("_mm") else 4)


def _status_msg(rec: FrameRecord) -> object:
    from ficap_ros.io.messages import ROSBAGS, header
    from ficap_ros.io.sources import jazzy_typestore

    t = jazzy_typestore().types
    level, message = record_status(rec)
    values = [(k, _status_text(k, v)) for k, v in status_values(rec).items()]
    status = t["diagnostic_msgs/msg/DiagnosticStatus"](
        level=level, name="ficap", message=message, hardware_id=rec.frame_id,
        values=[t["diagnostic_msgs/msg/KeyValue"](key=k, value=v) for k, v in values],
    )
    return t["diagnostic_msgs/msg/DiagnosticArray"](
        header=header(ROSBAGS, rec.stamp_ns, rec.frame_id), status=[status])


def _frame_messages(rec: FrameRecord, frames: OutputFrames,
                    homographies: np.ndarray | None = None) -> list[tuple[str, object]]:
    """(label stream, message) of one record, in the order they are written: the poses, the head
    angles and the TF of a posed frame; quality and status of every frame; the detections of
    every processed one (``homographies``: theirs, ``detections.apriltag_homographies``)."""
    from ficap_ros.io.detections import apriltag_array, fit_values
    from ficap_ros.io.frames import frame_transforms, pose_outputs, tf_message
    from ficap_ros.io.messages import ROSBAGS, header, named_values

    out: list[tuple[str, object]] = []
    if rec.T_cam_cap is not None and rec.T_frontal_head is not None:
        poses = pose_outputs(ROSBAGS, rec.stamp_ns, rec, frames)
        out += [("cap_pose", poses["cap"]), ("head_pose", poses["head"]),
                ("head_pose_cov", poses["head_cov"]), ("head_frontal", poses["head_frontal"]),
                ("head_rpy", poses["rpy_deg"]),
                ("tf", tf_message(ROSBAGS, rec.stamp_ns, frame_transforms(rec, frames))),
                *([("head_twist", poses["twist"])] if "twist" in poses else []),
                ("head_rpy_rad", poses["rpy_rad"])]
    in_camera = header(ROSBAGS, rec.stamp_ns, rec.frame_id)
    out += [("quality", named_values(ROSBAGS, in_camera, quality_values(rec))),
            ("status", _status_msg(rec))]
    if rec.tags is not None:
        out += [("detections", apriltag_array(ROSBAGS, in_camera, rec.tags, homographies)),
                ("detections_fit", named_values(ROSBAGS, in_camera, fit_values(rec.tags)))]
    return out


#: Records whose detections' homographies ``write_labels_bag`` solves at once (one solve's fixed cost
#: shared; the block bounds its (tags, 8, 8) systems' memory on long recordings).
_HOMOGRAPHY_BLOCK = 256


def write_labels_bag(path: str | Path, records: Sequence[FrameRecord],
                     namespace: str = DEFAULT_NAMESPACE,
                     frames: OutputFrames | None = None) -> None:
    """Write labels.mcap: a single-file rosbag2 MCAP, plus ``metadata.yaml`` beside it.

    The folder holding ``path`` is thus also a rosbag2 bag. Written atomically. ``frames``: the
    output frames (default: the camera's and the frontal frame, no mount); a mount goes on
    ``/tf_static`` with the first image of each camera frame.

    Raises:
        BagError: the folder is not writable.
    """
    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.io.detections import apriltag_homographies
    from ficap_ros.io.frames import static_transforms, tf_message
    from ficap_ros.io.messages import ROSBAGS

    frames = frames or OutputFrames()
    topics = label_topics(namespace)
    with BagWriter(path, storage="mcap", layout="file") as bag:
        for stream, msgtype in _TOPIC_TYPES.items():
            if stream != "tf_static" or frames.mount is not None:
                bag.add_topic(topics[stream], msgtype)
        static_for = None
        for start in range(0, len(records), _HOMOGRAPHY_BLOCK):
            block = records[start:start + _HOMOGRAPHY_BLOCK]
            homographies = iter(apriltag_homographies([r.tags for r in block if r.tags is not None]))
            for rec in block:
                if frames.mount is not None and rec.frame_id != static_for:
                    static_for = rec.frame_id
                    bag.write(topics["tf_static"], rec.stamp_ns, tf_message(
                        ROSBAGS, rec.stamp_ns, static_transforms(frames, rec.frame_id)))
                hom = next(homographies) if rec.tags is not None else None
                for stream, msg in _frame_messages(rec, frames, hom):
                    bag.write(topics[stream], rec.stamp_ns, msg)
