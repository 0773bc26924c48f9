"""What ``ficap_node`` does with one image, without ROS: build its pipeline from the settings,
decode the message, choose its intrinsics, run the pipeline, and make the frame's record
(``ficap_ros.io.labels.FrameRecord``, the labels' own, with its detections' fits) with what the
node adds to it (status level and message, whether its pose is published, the image and tags to
draw). The node only subscribes, publishes and serves.

Messages are read duck-typed (``ficap_ros.io.messages``), so tests and tools can drive this with
rosbags messages as well as rclpy's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ficap_ros.errors import ConfigError, FicapError, IntrinsicsError
from ficap_ros.geometry.camera import (
    CameraModel,
    CameraTiming,
    load_camera_timing,
    load_camera_yaml,
)
from ficap_ros.geometry.cap_model import load_model, nominal_model
from ficap_ros.io import messages
from ficap_ros.io.camera_info import CameraInfoCache
from ficap_ros.io.detections import tag_fits
from ficap_ros.io.labels import FrameRecord
from ficap_ros.io.status import (
    FrameStatus,
    quality_values,
    record_status,
    status_values,
)
from ficap_ros.stamps import stamp_to_ns
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.detector import TagDetection
from ficap_ros.vision.pipeline import FrameProcessor

__all__ = ["LiveFrame", "frame_processor", "apply_settings", "camera_timing", "failed_frame",
           "process_image", "reference_q_xyzw", "refusal_before_queueing"]


@dataclass(frozen=True)
class LiveFrame:
    """One image's outcome, as the node publishes it: the frame's record and the node's own.

    Attributes:
        record: the frame's record (the same values as labels.csv / labels.mcap).
        level, message: its status (``status.record_status`` under the node's
            ``warn_reliability``).
        search: how the tags were found ('' when the frame failed).
        detections: the tags found, with their corners (for the debug image).
        image: the decoded grey image (None when it failed).
        camera: the intrinsics used (None when it failed).
        publish_pose: the pose is published (there is one, reliable enough).
    """

    record: FrameRecord
    level: int
    message: str
    search: str = ""
    detections: tuple[TagDetection, ...] = ()
    image: np.ndarray | None = None
    camera: CameraModel | None = None
    publish_pose: bool = False

    @property
    def failed(self) -> bool:
        """The image could not be processed."""
        return self.record.status is FrameStatus.FAILED

    def quality_values(self, latency_ms: float) -> dict[str, float]:
        """The ``quality`` topic's numbers: labels.mcap's, and the latency (ms and s)."""
        return {**quality_values(self.record), "latency_ms": float(latency_ms),
                "latency_s": float(latency_ms) / 1000.0}

    def status_values(self, latency_ms: float, dropped_frames: int) -> dict[str, Any]:
        """The ``status`` topic's values: labels.mcap's, how the tags were found, the latency
        and the frames the mailbox dropped so far."""
        return {**status_values(self.record), "search": self.search, "latency_ms": latency_ms,
                "dropped_frames": dropped_frames}


def frame_processor(config: Any) -> FrameProcessor:
    """The pipeline of the node's settings (``ros.params.NodeConfig``: cap model, detector, pose,
    tracking, the camera's timing: ``camera_timing``).

    Raises:
        ModelError: an unreadable ``model_file``. ConfigError: bad detector settings, or a
        ``FICAP_MAX_PIXELS`` that is no number of pixels, or a malformed ``camera_timing`` in
        ``camera_info_file``.
    """
    from ficap_ros.io.image_codec import max_pixels

    max_pixels()  # a bad FICAP_MAX_PIXELS refuses the start, not every frame
    return FrameProcessor(model=load_model(config.model_file) if config.model_file else nominal_model(),
                          detector=config.detector_config, pose=config.pose_config,
                          tracking=config.tracking, timing=camera_timing(config))


def apply_settings(processor: FrameProcessor, config: Any) -> str:
    """Apply the settings a running pipeline takes from the next frame on (the node's parameters
    changed): the pose settings and the camera's timing (``camera_timing``).

    Returns:
        '' when applied; else one line saying why the camera's timing was kept (the
        ``camera_info_file`` changed under the running node into one whose ``camera_timing`` is
        malformed): a running node never dies of a file's content.
    """
    processor.pose_config = config.pose_config
    try:
        processor.timing = camera_timing(config)
    except FicapError as err:
        return f"camera timing kept: {err}"
    return ""


def camera_timing(config: Any) -> CameraTiming:
    """The camera's timing under the node's settings: the ``camera.*`` parameters when any is
    set (``NodeConfig.camera_timing``), else the ``camera_timing`` mapping of
    ``camera_info_file``, else ``CameraTiming()`` (not known).

    Raises:
        ConfigError: the file's intrinsics read but its ``camera_timing`` is malformed (a file
        that does not read at all is the CameraInfo cache's error, reported there).
    """
    if config.camera_timing is not None or not config.camera_info_file:
        return config.camera_timing or CameraTiming()
    try:
        return load_camera_timing(config.camera_info_file) or CameraTiming()
    except IntrinsicsError as err:
        try:
            load_camera_yaml(config.camera_info_file)
        except IntrinsicsError:
            return CameraTiming()
        raise ConfigError(str(err)) from None


def failed_frame(stamp_ns: int, frame_id: str, reason: str,
                 calibration: HeadCalibration) -> LiveFrame:
    """An image that could not be processed (ERROR status, ``reason`` as its message)."""
    rec = FrameRecord.unprocessed(0, stamp_ns, frame_id, reason, FrameStatus.FAILED, calibration)
    return LiveFrame(rec, *record_status(rec))


def refusal_before_queueing(msg: Any) -> str:
    """Why an image message is refused before it is queued ('' when it is not): a size above the
    pixel budget, from a raw image's fields or a compressed image's header
    (``image_codec.check_compressed``), so a hostile frame never costs the decode's memory.
    A header read; decoding finds everything else."""
    from ficap_ros.io.image_codec import check_compressed, check_pixel_budget

    try:
        if hasattr(msg, "format"):
            check_compressed(messages.as_bytes(msg.data))
        else:
            check_pixel_budget(int(msg.width), int(msg.height))
    except FicapError as err:
        return str(err)
    except (TypeError, ValueError, OverflowError) as err:
        return f"malformed image message: {err}"
    return ""


def process_image(msg: Any, processor: FrameProcessor, cameras: CameraInfoCache,
                  calibration: HeadCalibration, config: Any) -> LiveFrame:
    """One Image or CompressedImage message through the pipeline (errors become a failed frame).

    Args:
        msg: the image message (a CompressedImage has ``format``).
        calibration: the head calibration of the frame's record.
        config: the node's settings (``ros.params.NodeConfig``): ``camera_info_max_stamp_diff_ms``,
            ``image_is_rectified``, ``publish_min_reliability``, ``warn_reliability``.
    """
    header = msg.header
    stamp_ns = stamp_to_ns(header.stamp)
    try:
        image = (messages.compressed_to_array(msg) if hasattr(msg, "format")
                 else messages.image_to_array(msg))
        camera = cameras.camera_for(stamp_ns, int(config.camera_info_max_stamp_diff_ms * 1e6),
                                    config.image_is_rectified)
        camera.check_image_size(image.shape[1], image.shape[0])
        result = processor.process(image, camera, stamp_ns)
    except FicapError as err:
        return failed_frame(stamp_ns, header.frame_id, str(err), calibration)
    rec = FrameRecord.of(result, 0, stamp_ns, header.frame_id, calibration,
                         processor.pose_config.method,
                         tag_fits(result.detections, result.pose, processor.model, camera))
    return LiveFrame(rec, *record_status(rec, config.warn_reliability), str(result.search),
                     result.detections, image, camera,
                     publish_pose=(rec.pose is not None
                                   and rec.pose.reliability >= config.publish_min_reliability))


def reference_q_xyzw(msg: Any) -> np.ndarray | None:
    """A reference pose message's orientation as a unit quaternion (x, y, z, w), or None when it
    is not finite or (near) zero."""
    o = messages.orientation(msg)
    q = np.array([o.x, o.y, o.z, o.w], dtype=np.float64)
    if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-6:
        return None
    return q / np.linalg.norm(q)
