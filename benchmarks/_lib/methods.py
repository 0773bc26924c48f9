"""The pipelines the tables compare, defined once.

* ours: ``FrameProcessor`` with its defaults (ArUco search, unbiased edge-fit corners, joint pose,
  tracking), as ``ficap replay`` and the node run it;
* ours + photometric: the tag-level photometric corner step on every tag (``--photometric``; ours
  runs it on the tags noise limits only);
* the naive peer: what an afternoon's pipeline does: OpenCV's ArUco detector with sub-pixel
  corners, one SQPnP + Levenberg-Marquardt over every corner, no outlier handling, no tracking;
* AprilTag 3: pupil-apriltags, decimate 1, one thread, its own corners, with our joint pose.
"""

from __future__ import annotations

from dataclasses import dataclass

from ficap_ros.geometry.camera import CameraTiming
from ficap_ros.geometry.cap_model import CapModel, nominal_model
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pipeline import FrameProcessor
from ficap_ros.vision.pose import PoseConfig


@dataclass(frozen=True)
class Method:
    """One pipeline: detector settings, pose settings and whether it tracks between frames."""

    name: str
    detector: DetectorConfig
    pose: PoseConfig
    tracking: bool = True

    def processor(self, model: CapModel | None = None, timing: CameraTiming | None = None) -> FrameProcessor:
        """The pipeline for the cap ``model`` (default: the nominal cap) and a camera whose
        exposure and readout are ``timing`` (None: not stated, as a user who gives none)."""
        return FrameProcessor(model or nominal_model(), self.detector, self.pose, tracking=self.tracking,
                              timing=timing)


OURS = Method("ficap", DetectorConfig(), PoseConfig())
OURS_PHOTOMETRIC = Method("ficap + photometric", DetectorConfig(edge_photometric=True), PoseConfig())
OURS_PAPER = Method("ficap, paper's pose", DetectorConfig(), PoseConfig(method="paper"))
PEER = Method("naive peer", DetectorConfig(corner_refine="subpix"), PoseConfig(method="naive"), tracking=False)
AT3_DETECTOR = DetectorConfig(backend="apriltag", corner_refine="apriltag", quad_decimate=1.0)
AT3 = Method("AprilTag 3 decimate 1 + joint pose", AT3_DETECTOR, PoseConfig(), tracking=False)
