"""ROS messages written once, over their fields: stamps, headers, poses, head angles, named
values, CameraInfo, Image, CompressedImage, built from and read into the core types.

These are the only message builders: the live node and the bag tools call them directly with a
``MessageClasses`` that says where the message classes come from and how array fields are filled.
``ros.msgs.RCLPY`` feeds them rclpy's generated classes (the node); ``ROSBAGS`` feeds them the
rosbags Jazzy typestore's dataclasses (the bag writers, labels, synth, evaluation; no ROS install
needed). Readers are duck-typed: a message of either kind (or anything with the fields) goes in.
This module imports neither rclpy nor any ROS message package.

Quaternions in messages are the x, y, z, w fields (``q_xyzw``); translations are metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ImageError
from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.metrics import yaw_pitch_roll_deg, yaw_pitch_roll_rad
from ficap_ros.geometry.transform import Transform
from ficap_ros.io.image_codec import decode_compressed, decode_image, encoding_layout

__all__ = ["MessageClasses", "ROSBAGS", "jazzy_typestore", "vendored_msg_definitions", "as_bytes", "time", "header", "pose",
           "pose_stamped", "pose_with_covariance_stamped", "transform_stamped", "rpy_deg",
           "rpy_rad", "named_values", "twist_stamped", "twist_to_array",
           "camera_info", "image",
           "compressed_image", "image_to_array", "compressed_to_array", "orientation",
           "pose_to_transform", "UNKNOWN_COVARIANCE"]

#: What goes out for a covariance that is not finite: huge (1 m, 180 deg), never zeros ("exact").
UNKNOWN_COVARIANCE = np.diag([1.0, 1.0, 1.0, np.pi**2, np.pi**2, np.pi**2])


@dataclass(frozen=True)
class MessageClasses:
    """Where the builders get message classes, and how array fields take their values.

    Attributes:
        types: ``"pkg/msg/Name"`` -> message class (constructed with field keywords).
        floats: float64 array -> the value a ``float64[]`` / ``float64[N]`` field takes.
        octets: contiguous array -> the value a ``uint8[]`` field takes (its bytes).
    """

    types: Mapping[str, Any]
    floats: Callable[[np.ndarray], Any]
    octets: Callable[[np.ndarray], Any]


class _Typestore(Mapping[str, Any]):
    """The rosbags Jazzy typestore's classes, loaded on first use (the store's own mapping,
    looked up once: the builders ask for a class per message field)."""

    def __init__(self) -> None:
        self._types: Mapping[str, Any] | None = None

    def _classes(self) -> Mapping[str, Any]:
        if self._types is None:
            self._types = jazzy_typestore().types
        return self._types

    def __getitem__(self, name: str) -> Any:
        return self._classes()[name]

    def __iter__(self) -> Any:
        return iter(self._classes())

    def __len__(self) -> int:
        return len(self._classes())


_TYPESTORE: Any = None


def jazzy_typestore() -> Any:
    """rosbags' ROS 2 Jazzy typestore with the vendored apriltag_msgs definitions (cached)."""
    global _TYPESTORE
    if _TYPESTORE is None:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        store = get_typestore(Stores.ROS2_JAZZY)
        for name, text in vendored_msg_definitions().items():
            store.register(get_types_from_msg(text, name))
        _TYPESTORE = store
    return _TYPESTORE


def vendored_msg_definitions() -> dict[str, str]:
    """The message definitions vendored in ``ficap_ros/interfaces`` that rosbags' Jazzy store
    lacks (apriltag_msgs: labels.mcap's ``detections``), ``pkg/msg/Name`` -> .msg text, each
    after the ones it uses."""
    from importlib import resources

    folder = resources.files("ficap_ros") / "interfaces" / "apriltag_msgs" / "msg"
    return {f"apriltag_msgs/msg/{name}": (folder / f"{name}.msg").read_text()
            for name in ("Point", "AprilTagDetection", "AprilTagDetectionArray")}


#: rosbags' dataclasses: array fields are numpy arrays of their own (CDR serialises them as is).
ROSBAGS = MessageClasses(
    types=_Typestore(),
    floats=lambda a: np.asarray(a, dtype=np.float64).reshape(-1).copy(),
    octets=lambda a: np.ascontiguousarray(a).view(np.uint8).reshape(-1).copy(),
)


def as_bytes(data: object) -> np.ndarray:
    """A message's ``uint8[]`` data (array.array, bytes, numpy, list) as a uint8 array, without a
    copy when possible."""
    try:
        return np.frombuffer(data, dtype=np.uint8)  # type: ignore[call-overload]
    except TypeError:
        return np.asarray(data, dtype=np.uint8).reshape(-1)


# -- building -------------------------------------------------------------------------------------
def time(c: MessageClasses, stamp_ns: int) -> Any:
    """``builtin_interfaces/Time`` of integer nanoseconds."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return c.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def header(c: MessageClasses, stamp_ns: int, frame_id: str) -> Any:
    """``std_msgs/Header`` (stamp from integer nanoseconds)."""
    return c.types["std_msgs/msg/Header"](stamp=time(c, stamp_ns), frame_id=frame_id)


def pose(c: MessageClasses, T: Transform) -> Any:
    """``geometry_msgs/Pose`` of a transform (translation in metres)."""
    x, y, z = T.translation_m.tolist()  # Python floats, one call per array
    qx, qy, qz, qw = T.q_xyzw.tolist()
    return c.types["geometry_msgs/msg/Pose"](
        position=c.types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=c.types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))


def pose_stamped(c: MessageClasses, head: Any, T: Transform) -> Any:
    """``geometry_msgs/PoseStamped`` of ``T`` with the header ``head``."""
    return c.types["geometry_msgs/msg/PoseStamped"](header=head, pose=pose(c, T))


def pose_with_covariance_stamped(c: MessageClasses, head: Any, T: Transform,
                                 covariance: np.ndarray) -> Any:
    """``geometry_msgs/PoseWithCovarianceStamped``; ``covariance`` is 6x6 in ROS order (x y z rx
    ry rz). A non-finite one goes out as ``UNKNOWN_COVARIANCE``, never as zeros."""
    cov = np.asarray(covariance, dtype=np.float64).reshape(36)
    if not np.all(np.isfinite(cov)):
        cov = UNKNOWN_COVARIANCE.reshape(36)
    return c.types["geometry_msgs/msg/PoseWithCovarianceStamped"](
        header=head, pose=c.types["geometry_msgs/msg/PoseWithCovariance"](
            pose=pose(c, T), covariance=c.floats(cov)))


def transform_stamped(c: MessageClasses, head: Any, child_frame_id: str, T: Transform) -> Any:
    """``geometry_msgs/TransformStamped``: ``T`` is T_parent_child, the parent ``head.frame_id``
    (translation in metres)."""
    x, y, z = T.translation_m.tolist()
    qx, qy, qz, qw = T.q_xyzw.tolist()
    return c.types["geometry_msgs/msg/TransformStamped"](
        header=head, child_frame_id=child_frame_id,
        transform=c.types["geometry_msgs/msg/Transform"](
            translation=c.types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z),
            rotation=c.types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw)))


def _rpy(c: MessageClasses, head: Any, ypr: np.ndarray) -> Any:
    yaw, pitch, roll = np.asarray(ypr, dtype=np.float64).reshape(3).tolist()
    return c.types["geometry_msgs/msg/Vector3Stamped"](
        header=head, vector=c.types["geometry_msgs/msg/Vector3"](x=roll, y=pitch, z=yaw))


def rpy_deg(c: MessageClasses, head: Any, R_frontal_head: Rotation) -> Any:
    """``geometry_msgs/Vector3Stamped`` of the head angles in degrees: x roll, y pitch, z yaw
    (each about its axis, REP-103 right-hand, intrinsic ZYX: tf2's ``getRPY``); pitch positive
    nose down."""
    return _rpy(c, head, yaw_pitch_roll_deg(R_frontal_head))


def rpy_rad(c: MessageClasses, head: Any, R_frontal_head: Rotation) -> Any:
    """``rpy_deg`` in radians (REP-103's unit)."""
    return _rpy(c, head, yaw_pitch_roll_rad(R_frontal_head))


def twist_stamped(c: MessageClasses, head: Any, twist: np.ndarray) -> Any:
    """``geometry_msgs/TwistStamped`` of a (6,) twist in ROS order: the linear velocity (m/s),
    then the angular velocity (rad/s), both in the axes of ``head``'s frame."""
    v = np.asarray(twist, dtype=np.float64).reshape(6).tolist()
    vector = c.types["geometry_msgs/msg/Vector3"]
    return c.types["geometry_msgs/msg/TwistStamped"](
        header=head, twist=c.types["geometry_msgs/msg/Twist"](
            linear=vector(x=v[0], y=v[1], z=v[2]), angular=vector(x=v[3], y=v[4], z=v[5])))


def named_values(c: MessageClasses, head: Any, values: Mapping[str, float]) -> Any:
    """Per-frame numbers as a ``sensor_msgs/JointState``: ``name[i]`` labels ``position[i]``.

    JointState is the standard stamped message of named numbers that Foxglove and PlotJuggler
    plot by name; velocity and effort stay empty. NaN where a value does not exist (no pose).
    """
    return c.types["sensor_msgs/msg/JointState"](
        header=head, name=list(values),
        position=c.floats(np.array([float(v) for v in values.values()], dtype=np.float64)),
        velocity=c.floats(np.zeros(0)), effort=c.floats(np.zeros(0)))


def camera_info(c: MessageClasses, head: Any, camera: CameraModel) -> Any:
    """``sensor_msgs/CameraInfo`` of a camera model (R = I, P = [K | 0]; no distortion is written
    as plumb_bob with five zeros, what camera drivers publish)."""
    model = "plumb_bob" if camera.distortion_model == "none" else camera.distortion_model
    d = camera.D if camera.D.size else np.zeros(5)
    return c.types["sensor_msgs/msg/CameraInfo"](
        header=head, height=camera.height_px, width=camera.width_px, distortion_model=model,
        d=c.floats(d), k=c.floats(camera.K), r=c.floats(np.eye(3)),
        p=c.floats(np.hstack([camera.K, np.zeros((3, 1))])), binning_x=0, binning_y=0,
        roi=c.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                        width=0, do_rectify=False))


def image(c: MessageClasses, head: Any, array: np.ndarray, encoding: str) -> Any:
    """``sensor_msgs/Image`` of an array already laid out for ``encoding`` (rows unpadded;
    ``is_bigendian`` from the array's byte order).

    Raises:
        ImageError: an encoding ``image_codec`` does not decode, or an array whose channels or
            sample size do not match it.
    """
    channels, depth = encoding_layout(encoding)
    arr = np.ascontiguousarray(array)
    if arr.dtype.itemsize != depth or (arr.shape[2] if arr.ndim == 3 else 1) != channels:
        raise ImageError(f"array {arr.shape} {arr.dtype} does not match encoding {encoding}")
    return c.types["sensor_msgs/msg/Image"](
        header=head, height=int(arr.shape[0]), width=int(arr.shape[1]), encoding=encoding,
        is_bigendian=int(arr.dtype.byteorder == ">"), step=int(arr.strides[0]),
        data=c.octets(arr))


def compressed_image(c: MessageClasses, head: Any, data: bytes, fmt: str = "jpeg") -> Any:
    """``sensor_msgs/CompressedImage`` of encoded bytes (``fmt``: jpeg, png, ...)."""
    return c.types["sensor_msgs/msg/CompressedImage"](
        header=head, format=fmt, data=c.octets(np.frombuffer(data, np.uint8)))


# -- reading (duck-typed: rclpy or rosbags messages) ----------------------------------------------
def image_to_array(msg: Any) -> np.ndarray:
    """A ``sensor_msgs/Image`` as a grey array: uint8, or uint16 (native order) for 16-bit data
    (``image_codec.decode_image``: honours ``step`` and ``is_bigendian``).

    Raises:
        ImageError: unknown encoding, zero size, a short step, or data not ``step * height`` long.
    """
    return decode_image(str(msg.encoding), int(msg.height), int(msg.width), int(msg.step),
                        as_bytes(msg.data), bool(msg.is_bigendian))


def compressed_to_array(msg: Any) -> np.ndarray:
    """A ``sensor_msgs/CompressedImage`` decoded to grey uint8.

    Raises:
        ImageError: empty or undecodable data.
    """
    return decode_compressed(as_bytes(msg.data), str(msg.format))


def orientation(msg: Any) -> Any:
    """The orientation of a PoseStamped, PoseWithCovarianceStamped, Odometry,
    QuaternionStamped or TransformStamped (an object with x, y, z, w)."""
    if hasattr(msg, "quaternion"):
        return msg.quaternion
    if hasattr(msg, "transform"):
        return msg.transform.rotation
    p = msg.pose
    p = p.pose if hasattr(p, "pose") else p  # WithCovariance / Odometry
    return p.orientation


def twist_to_array(msg: Any) -> np.ndarray:
    """A Twist or TwistStamped as (6,): linear (m/s), then angular (rad/s)."""
    t = msg.twist if hasattr(msg, "twist") else msg
    return np.array([t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z],
                    dtype=np.float64)


def pose_to_transform(msg: Any) -> Transform:
    """A Pose, PoseStamped or PoseWithCovariance(Stamped) as a ``Transform`` (metres)."""
    p = msg
    while not hasattr(p, "position"):
        p = p.pose
    o = p.orientation
    return Transform(Rotation.from_quat([o.x, o.y, o.z, o.w]),
                     np.array([p.position.x, p.position.y, p.position.z], dtype=np.float64))

