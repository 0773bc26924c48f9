"""Offline frames solved with the next frame's pose (``ficap_ros.vision.two_sided``).

Rendered frames of a glance through a rolling shutter with motion blur (the ``glance_rs_drive``
fixture): each frame held until the next one is in, returned once and in order; solved again with
its neighbours it is closer to the truth in the fast frames than the causal model's; the run's last
frame, without a next one, and every frame of a camera without a stated timing keep their first
result.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rolling_shutter import bag_truths

from ficap_ros.geometry.camera import CameraTiming
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.io.sources import decode_raw, open_frames
from ficap_ros.vision.pipeline import FrameProcessor, FrameResult
from ficap_ros.vision.two_sided import TwoSidedFrames


def _run(bag: Path, enabled: bool, timing: CameraTiming | None = None,
         cut_at: int | None = None) -> tuple[list[FrameResult], list[int], np.ndarray, np.ndarray]:
    """Every frame's result, the keys in the order they came back, and the rotation error
    (deg) and true angular speed (deg/s) per frame; ``cut_at``: ``finish`` before that frame."""
    truths = bag_truths(bag)
    source = open_frames(bag)
    proc = FrameProcessor(nominal_model(), timing=source.timing if timing is None else timing)
    frames: TwoSidedFrames[int] = TwoSidedFrames(proc, enabled=enabled)
    raws = list(source.raw_frames())
    out: dict[int, FrameResult] = {}
    order: list[int] = []
    for i, raw in enumerate(raws):
        finished = frames.finish() if i == cut_at else []
        finished += frames.process(i, decode_raw(raw), raw.camera, raw.stamp_ns)
        for k, r in finished:
            order.append(k)
            out[k] = r
    for k, r in frames.finish():
        order.append(k)
        out[k] = r
    results = [out[k] for k in range(len(raws))]
    rot = np.array([angle_deg(r.pose.T_cam_cap.rotation, truths[raw.stamp_ns][0].rotation)
                    if r.pose is not None else np.inf for r, raw in zip(results, raws)])
    speed = np.array([truths[raw.stamp_ns][1] for raw in raws])
    return results, order, rot, speed


def _same(a: FrameResult, b: FrameResult) -> bool:
    """Whether two results have the very same pose (bit for bit)."""
    assert a.pose is not None and b.pose is not None
    return bool(np.array_equal(a.pose.T_cam_cap.matrix, b.pose.T_cam_cap.matrix))


def test_two_sided_frames_are_closer_in_the_fast_frames(glance_rs_drive: Path) -> None:
    """Every frame back once and in order, a pose in each; the fast frames' (90 deg/s and over)
    mean rotation error is lower than the causal model's by a tenth and more, the slow frames'
    stays where it was; the last frame has no next one and keeps its first result."""
    causal, order_c, rot_c, speed = _run(glance_rs_drive, enabled=False)
    two, order, rot, _ = _run(glance_rs_drive, enabled=True)
    n = len(speed)
    assert order == list(range(n)) and order_c == list(range(n))
    assert np.all(np.isfinite(rot))
    fast, slow = speed >= 90.0, speed < 30.0
    print(f"fast mean {np.mean(rot_c[fast]):.4f} -> {np.mean(rot[fast]):.4f} deg, "
          f"slow median {np.median(rot_c[slow]):.4f} -> {np.median(rot[slow]):.4f}")
    assert fast.sum() >= 5 and slow.sum() >= 10
    assert np.mean(rot[fast]) < 0.9 * np.mean(rot_c[fast])
    assert np.median(rot[slow]) < 1.2 * np.median(rot_c[slow]) + 0.001
    assert _same(two[-1], causal[-1])
    assert _same(two[0], causal[0])  # no past pose: not two-sided
    # The causal model's velocity is the backward one; the two-sided frames report theirs.
    assert any(not np.array_equal(a.pose.velocity, b.pose.velocity) for a, b in zip(two, causal))


def test_a_cut_and_no_timing_keep_the_first_results(glance_rs_drive: Path) -> None:
    """``finish`` before frame 12 (a cut): frame 11 has no next one and keeps its causal result,
    the frames around it are solved with their neighbours as before. A camera with no stated
    timing has no motion model: every frame as the causal run gives it."""
    causal, _, _, _ = _run(glance_rs_drive, enabled=False)
    whole, _, _, _ = _run(glance_rs_drive, enabled=True)
    cut, order, _, _ = _run(glance_rs_drive, enabled=True, cut_at=12)
    assert order == list(range(len(causal)))
    assert _same(cut[11], causal[11])
    assert not _same(whole[11], causal[11])
    assert _same(cut[10], whole[10])
    plain, _, _, _ = _run(glance_rs_drive, enabled=False, timing=CameraTiming())
    untimed, _, _, _ = _run(glance_rs_drive, enabled=True, timing=CameraTiming())
    for a, b in zip(plain, untimed):
        assert _same(a, b) and b.pose.velocity is None
