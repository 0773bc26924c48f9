"""Reader of blender_dev (``<data>/blender_dev``): path-traced renders of the cap with exact truth.

The sets are independent of ``ficap_ros.tools.synth`` (Blender/Cycles, a lens PSF in linear light,
shot and read noise, clipping, a tone curve, JPEG), so they check corners and poses on images the
package did not make. They are a check, not a training set: nothing in the package is tuned to them.
Each set is a rosbag2 (MCAP) read through ``ficap_ros.io.sources`` (the code path replay uses) plus
``ground_truth.json`` (documented in the set's README). ``datasets/cycles_render.py`` writes sets in
the same format.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.io.sources import decode_raw, open_frames

#: Every set, in the README's order.
SETS = (
    "dev_540p_neutral",
    "dev_540p_high",
    "dev_540p_low",
    "dev_1080p_neutral",
    "dev_1080p_high",
    "dev_1080p_neutral_asbuilt",
    "dev_540p_drive30",
    "dev_1080p_drive30",
    "dev_540p_glance_blur",
    "dev_540p_glance_rs",
)


@dataclass(frozen=True)
class TagTruth:
    """What the renderer knows of one tag in one frame."""

    tag_id: int
    facing: bool
    view_angle_deg: float
    corners_visible: int  # 0..4 corners not hidden (ray cast against the whole scene)


@dataclass(frozen=True)
class DevFrame:
    """One frame: the decoded grey image and its exact ground truth."""

    index: int
    stamp_ns: int
    image: np.ndarray
    T_cam_cap: Transform
    corners_px: dict[int, np.ndarray]  # tag id -> (4, 2) projected true corners (OpenCV order)
    tags: dict[int, TagTruth]

    def clean_ids(self, max_view_angle_deg: float = 70.0) -> list[int]:
        """Tags fully visible (4 corners), facing the camera, within ``max_view_angle_deg``."""
        return sorted(t.tag_id for t in self.tags.values()
                      if t.facing and t.corners_visible == 4 and t.view_angle_deg <= max_view_angle_deg)


@dataclass(frozen=True)
class DevSet:
    name: str
    path: Path
    camera: CameraModel
    true_model: CapModel  # the cap that was rendered (as built for the as-built set)
    psf_sigma_px: float
    tone: str
    lighting: str
    frames: tuple[DevFrame, ...]
    timing: CameraTiming = CameraTiming()  # exposure and readout as ground_truth.json states them


def timing_of(truth: dict) -> CameraTiming:
    """The camera timing a set's ``ground_truth.json`` states (``exposure_s``, ``readout_s``; the
    rows read top to bottom, the stamp the middle row's mid-exposure, as its README says): a
    still set's, with neither, is the unknown timing (``CameraTiming()``)."""
    return CameraTiming(exposure_ms=1e3 * float(truth.get("exposure_s") or 0.0),
                        readout_ms=1e3 * float(truth.get("readout_s") or 0.0))


def root_of(data: Path) -> Path:
    return data / "blender_dev"


def available(data: Path) -> bool:
    return root_of(data).is_dir()


def present(data: Path, names: tuple[str, ...] = SETS) -> list[str]:
    """The sets of ``names`` found under ``data``."""
    return [n for n in names if (root_of(data) / n / "ground_truth.json").is_file()]


def _transform(m: list) -> Transform:
    return Transform.from_matrix(np.asarray(m, dtype=np.float64))


def load_set(data: Path, name: str, max_frames: int | None = None) -> DevSet:
    """Read one set (the first ``max_frames`` frames when given): frames decoded by
    ``ficap_ros.io.sources`` and matched to the truth by stamp."""
    path = root_of(data) / name
    truth = json.loads((path / "ground_truth.json").read_text())
    corners_mm = np.asarray(truth["cap_corners_mm"], dtype=np.float64).reshape(-1, 4, 3)
    # ground_truth.json lists tag i's corners at rows 4i..4i+3 (ids 0..22 in order).
    true_model = CapModel(tuple(range(len(corners_mm))), corners_mm)
    by_stamp = {int(f["stamp_ns"]): f for f in truth["frames"]}
    frames: list[DevFrame] = []
    camera = None
    for raw in open_frames(path).raw_frames():
        gt = by_stamp.get(int(raw.stamp_ns))
        if gt is None:
            continue
        if max_frames is not None and len(frames) >= max_frames:
            break
        camera = raw.camera
        T_cam_cap = _transform(gt["T_cam_cap"])
        px = raw.camera.project(T_cam_cap.apply(corners_mm.reshape(-1, 3) / 1000.0)).reshape(-1, 4, 2)
        tags = {int(t["id"]): TagTruth(int(t["id"]), bool(t["facing"]), float(t["view_angle_deg"]),
                                       int(t["corners_visible"])) for t in gt["tags"]}
        frames.append(DevFrame(index=len(frames), stamp_ns=int(raw.stamp_ns), image=decode_raw(raw),
                               T_cam_cap=T_cam_cap, corners_px={tid: px[tid] for tid in tags}, tags=tags))
    render = truth.get("render", {})
    return DevSet(name=name, path=path, camera=camera, true_model=true_model,
                  psf_sigma_px=float(render.get("psf_sigma_px", float("nan"))),
                  tone=str(render.get("tone", "")), lighting=str(truth.get("lighting", "")),
                  frames=tuple(frames), timing=timing_of(truth))
