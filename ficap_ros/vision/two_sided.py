"""Offline frames solved with the next frame's pose too: the cap's path interpolated, not extrapolated.

Live, a frame's motion model (the rolling-shutter solve's velocity and acceleration, the
motion-aware corners' paths) can only come from the poses before it (``vision.motion``): through a
glance's acceleration such an extrapolation lags the cap's path. Offline the next frame is known.
``TwoSidedFrames`` holds each frame back until the next one has its (first) pose, then solves it
again with that pose as well (``FrameProcessor.resolve``, ``MotionPrior.two_sided``): the
neighbours are the poses of the frames before as the tracker remembers them and the next frame's
first pose, so tracking itself stays causal and every frame is solved at most twice.

A frame is solved again only where its motion model applies (the camera's timing states an
exposure or a readout, a past pose, and the next frame posed within ``MotionConfig.max_age_s`` of
the same camera); every other frame keeps its first result. ``finish`` ends a run of frames (a cut:
a segment's end, a reset of tracking): its last frame has no next one and keeps its first result,
so no neighbour is taken across a cut.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.vision.motion import PastPose
from ficap_ros.vision.pipeline import FrameProcessor, FrameResult, FrameSolve

__all__ = ["TwoSidedFrames"]

Key = TypeVar("Key")


@dataclass(frozen=True)
class _Held(Generic[Key]):
    """A frame waiting for the next one: the caller's key, its first result and what it was
    solved from (None: no pose), its stamp, ns, and camera."""

    key: Key
    result: FrameResult
    solve: FrameSolve | None
    stamp_ns: int
    camera: CameraModel


class TwoSidedFrames(Generic[Key]):
    """A ``FrameProcessor``'s frames, each finished once the next one is in (module docstring).

    Args:
        processor: the pipeline (with tracking; its ``timing`` the recording's).
        enabled: False: every frame's first result, at once (the causal model, as live).
    """

    def __init__(self, processor: FrameProcessor, enabled: bool = True) -> None:
        self.processor = processor
        self.enabled = enabled
        self._held: _Held[Key] | None = None

    def process(self, key: Key, image: np.ndarray, camera: CameraModel,
                stamp_ns: int) -> list[tuple[Key, FrameResult]]:
        """One frame in (``FrameProcessor.process``; raises its ``ImageError``, the held frame
        then still waits for a next one); out, in order, the frames finished by it: the held
        frame (solved again with this frame's pose where that applies) and, when not enabled,
        this one. ``key`` is the caller's, returned with the frame's result."""
        result = self.processor.process(image, camera, stamp_ns)
        solve = self.processor.last_solve
        if not self.enabled:
            return [(key, result)]
        out = [] if self._held is None else [self._finish(self._held, result, camera, stamp_ns)]
        self._held = _Held(key, result, solve, int(stamp_ns), camera)
        return out

    def finish(self) -> list[tuple[Key, FrameResult]]:
        """The held frame (none when nothing is held), with its first result: a cut follows."""
        held, self._held = self._held, None
        return [] if held is None else [(held.key, held.result)]

    def _finish(self, held: _Held[Key], following: FrameResult, camera: CameraModel,
                stamp_ns: int) -> tuple[Key, FrameResult]:
        """``held`` solved again with the pose of the frame after it, ``following`` (of
        ``camera`` at ``stamp_ns``), where both are posed, of the same camera and stamped in
        order."""
        pose = following.pose
        if (pose is None or held.solve is None or camera != held.camera or not held.stamp_ns
                or stamp_ns <= held.stamp_ns):
            return held.key, held.result
        after = PastPose(-(stamp_ns - held.stamp_ns) * 1e-9, pose.T_cam_cap, pose.covariance)
        return held.key, self.processor.resolve(held.result, held.solve, after)
