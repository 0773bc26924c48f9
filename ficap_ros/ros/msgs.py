"""The node's messages: rclpy's classes for ``ficap_ros.io.messages`` (``RCLPY``), and the
messages only the node publishes (DiagnosticArray, MarkerArray, a debug Image).

Headers, poses, head angles, named values, CameraInfo and images are built and read by
``ficap_ros.io.messages``'s functions over ``RCLPY``; CameraInfo becomes a ``CameraModel`` by
``ficap_ros.io.camera_info.camera_from_info``; frame records become the pose messages by
``ficap_ros.io.frames.pose_outputs``. Quaternions in messages are the x, y, z, w fields
(``q_xyzw``).
"""

from __future__ import annotations

import importlib
from typing import Any, Iterator, Mapping

import cv2
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point
from sensor_msgs.msg import Image
from std_msgs.msg import Header
from visualization_msgs.msg import Marker, MarkerArray

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.io import messages
from ficap_ros.io.labels import FrameRecord
from ficap_ros.stamps import stamp_to_ns
from ficap_ros.vision.detector import TagDetection

__all__ = [
    "RCLPY",
    "stamp_to_ns",
    "diagnostic_status",
    "diagnostic_array",
    "markers_msg",
    "debug_image_msg",
    "LEVEL_OK",
    "LEVEL_WARN",
    "LEVEL_ERROR",
]

LEVEL_OK = DiagnosticStatus.OK
LEVEL_WARN = DiagnosticStatus.WARN
LEVEL_ERROR = DiagnosticStatus.ERROR


class _RclpyTypes(Mapping[str, Any]):
    """rclpy's generated message classes by ``pkg/msg/Name`` (imported on first use)."""

    def __getitem__(self, name: str) -> Any:
        pkg, _, cls = name.split("/")
        return getattr(importlib.import_module(f"{pkg}.msg"), cls)

    def __iter__(self) -> Iterator[str]:
        return iter(())

    def __len__(self) -> int:
        return 0


#: rclpy's classes for ``ficap_ros.io.messages``: float arrays as lists (what the generated setters
#: check), byte arrays as bytes.
RCLPY = messages.MessageClasses(
    types=_RclpyTypes(),
    floats=lambda a: [float(v) for v in np.asarray(a, dtype=np.float64).reshape(-1)],
    octets=lambda a: np.ascontiguousarray(a).tobytes(),
)


# -- diagnostics ---------------------------------------------------------------------------------
def _fmt(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def diagnostic_status(
    name: str, level: bytes, message: str, values: Mapping[str, object], hardware_id: str = ""
) -> DiagnosticStatus:
    """One ``DiagnosticStatus`` with key/values formatted as strings."""
    return DiagnosticStatus(
        level=level, name=name, message=message, hardware_id=hardware_id,
        values=[KeyValue(key=k, value=_fmt(v)) for k, v in values.items()],
    )


def diagnostic_array(header: Header, *statuses: DiagnosticStatus) -> DiagnosticArray:
    """A ``DiagnosticArray`` of the statuses with the given header."""
    return DiagnosticArray(header=header, status=list(statuses))


# -- visualisation -------------------------------------------------------------------------------
def _point(p: np.ndarray) -> Point:
    return Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def markers_msg(
    header: Header, model: CapModel, record: FrameRecord, axis_length_m: float = 0.1
) -> MarkerArray:
    """Tag outlines (used tags green, others grey) and the head axes (x red, y green, z blue).

    Without a pose the array only deletes the previous markers.
    """
    out = MarkerArray()
    out.markers.append(Marker(header=header, ns="ficap", action=Marker.DELETEALL))
    pose, T = record.pose, record.T_cam_head
    if pose is None or T is None:
        return out
    used = set(pose.used_ids)
    corners_cam = pose.T_cam_cap.apply(np.asarray(model.corners_mm, dtype=np.float64) / 1000.0)
    for i, tag_id in enumerate(model.ids):
        m = Marker(header=header, ns="ficap_tags", id=int(tag_id), type=Marker.LINE_STRIP,
                   action=Marker.ADD)
        m.pose.orientation.w = 1.0
        m.scale.x = 0.002
        c = corners_cam[i]
        m.points = [_point(c[j % 4]) for j in range(5)]
        on = int(tag_id) in used
        m.color.r, m.color.g, m.color.b, m.color.a = (0.1, 0.9, 0.1, 1.0) if on else (0.5, 0.5, 0.5, 0.6)
        out.markers.append(m)
    origin = T.translation_m
    for axis in range(3):
        m = Marker(header=header, ns="ficap_head_axes", id=axis, type=Marker.ARROW,
                   action=Marker.ADD)
        m.pose.orientation.w = 1.0
        tip = origin + T.rotation.apply(np.eye(3)[axis]) * axis_length_m
        m.points = [_point(origin), _point(tip)]
        m.scale.x, m.scale.y, m.scale.z = 0.006, 0.012, 0.02
        rgb = np.eye(3)[axis]
        m.color.r, m.color.g, m.color.b, m.color.a = float(rgb[0]), float(rgb[1]), float(rgb[2]), 1.0
        out.markers.append(m)
    return out


def debug_image_msg(
    gray: np.ndarray, detections: tuple[TagDetection, ...], T_cam_head: Transform | None,
    camera: CameraModel | None, header: Header, axis_length_m: float = 0.1,
) -> Image:
    """A bgr8 image: detected corners and ids (OpenCV's drawing) and the head axes at
    ``T_cam_head`` (``gray``: the decoded image, uint8 or uint16; of a multi-channel one the first
    channel)."""
    gray = gray if gray.ndim == 2 else gray[:, :, 0]
    img = gray if gray.dtype == np.uint8 else (gray >> 8).astype(np.uint8)
    bgr = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if detections:
        corners = [d.corners_px.reshape(1, 4, 2).astype(np.float32) for d in detections]
        ids = np.array([[d.tag_id] for d in detections], dtype=np.int32)
        cv2.aruco.drawDetectedMarkers(bgr, corners, ids)
    if T_cam_head is not None and camera is not None:
        T = T_cam_head
        pts = np.vstack([T.translation_m, T.apply(np.eye(3) * axis_length_m)])
        if np.all(pts[:, 2] > 0):
            px = camera.project(pts)
            if np.all(np.isfinite(px)):
                o = tuple(int(round(v)) for v in px[0])
                for axis, colour in enumerate([(0, 0, 255), (0, 255, 0), (255, 0, 0)]):
                    tip = tuple(int(round(v)) for v in px[axis + 1])
                    cv2.line(bgr, o, tip, colour, 2, cv2.LINE_AA)
    return messages.image(RCLPY, header, bgr, "bgr8")

