"""Reader of ``../shared/data/blender_dev``: path-traced renders of the cap with exact ground truth.

The sets are independent of ``ficap_ros.tools.synth`` (Blender/Cycles, a lens PSF in linear light, shot
and read noise, clipping, a tone curve, JPEG), so they check our corners and poses on images we did
not make. They are a check, not a training set: nothing in the package is tuned to them.

Each set is a rosbag2 (MCAP) read through ``ficap_ros.io.sources`` (the code path replay uses) plus
``ground_truth.json`` (documented in the set's README). Benchmarks only: tests never read
``../shared``.

    from blender_dev import load_set, SETS
    s = load_set("dev_540p_neutral")
    for f in s.frames: f.image, f.T_cam_cap, f.corners_px[tag_id], f.tags[tag_id].view_angle_deg
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.io.sources import decode_raw, open_frames

ROOT = Path(__file__).resolve().parents[1]
#: ../shared next to the clone (or next to its parent: a git worktree one level further down).
BLENDER_DEV = next((p / "shared" / "data" / "blender_dev" for p in ROOT.parents[:2]
                    if (p / "shared" / "data" / "blender_dev").is_dir()),
                   ROOT.parent / "shared" / "data" / "blender_dev")
#: Every set, in the README's order.
SETS = (
    "dev_540p_neutral",
    "dev_540p_high",
    "dev_540p_low",
    "dev_1080p_neutral",
    "dev_1080p_high",
    "dev_1080p_neutral_asbuilt",
    "dev_540p_drive30",
)
#: ``FICAP_DEV_ROOT=<folder>`` points this reader (and every benchmark that uses ``BLENDER_DEV`` and
#: ``SETS``) at other sets in the same format, e.g. ``cycles_render.py``'s path-traced calibration
#: sets: ``SETS`` becomes the folder's sets (sub-folders with a ground_truth.json), in
#: ``<folder>/sets.txt``'s order if there is one, else sorted. Unset: blender_dev, as above.
if os.environ.get("FICAP_DEV_ROOT"):
    BLENDER_DEV = Path(os.environ["FICAP_DEV_ROOT"])
    _order = BLENDER_DEV / "sets.txt"
    SETS = tuple(_order.read_text().split()) if _order.is_file() else tuple(
        sorted(p.name for p in BLENDER_DEV.iterdir() if (p / "ground_truth.json").is_file())
        if BLENDER_DEV.is_dir() else ())


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
    T_cam_head: Transform
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
    truth: dict  # the whole ground_truth.json


def available() -> bool:
    return BLENDER_DEV.is_dir()


def _transform(m: list) -> Transform:
    a = np.asarray(m, dtype=np.float64)
    return Transform(Rotation.from_matrix(a[:3, :3]), a[:3, 3])


def load_set(name: str, root: Path = BLENDER_DEV) -> DevSet:
    """Read one set: frames decoded by ``ficap_ros.io.sources`` and matched to the truth by stamp."""
    path = root / name
    truth = json.loads((path / "ground_truth.json").read_text())
    corners_mm = np.asarray(truth["cap_corners_mm"], dtype=np.float64).reshape(-1, 4, 3)
    # ground_truth.json lists tag i's corners at rows 4i..4i+3 (ids 0..22 in order).
    true_model = CapModel(tuple(range(len(corners_mm))), corners_mm)
    by_stamp = {int(f["stamp_ns"]): f for f in truth["frames"]}
    src = open_frames(path)
    frames = []
    for raw in src.raw_frames():
        gt = by_stamp.get(int(raw.stamp_ns))
        if gt is None:
            continue
        image = decode_raw(raw)
        T_cam_cap = _transform(gt["T_cam_cap"])
        pts = T_cam_cap.apply(corners_mm.reshape(-1, 3) / 1000.0)
        px = raw.camera.project(pts).reshape(-1, 4, 2)
        tags = {int(t["id"]): TagTruth(int(t["id"]), bool(t["facing"]), float(t["view_angle_deg"]),
                                       int(t["corners_visible"])) for t in gt["tags"]}
        frames.append(DevFrame(
            index=len(frames), stamp_ns=int(raw.stamp_ns), image=image, T_cam_cap=T_cam_cap,
            T_cam_head=_transform(gt["T_cam_head"]),
            corners_px={tid: px[tid] for tid in tags},
            tags=tags,
        ))
    camera = next(iter(src.raw_frames())).camera
    render = truth.get("render", {})
    return DevSet(name=name, path=path, camera=camera, true_model=true_model,
                  psf_sigma_px=float(render.get("psf_sigma_px", float("nan"))),
                  tone=str(render.get("tone", "")), lighting=str(truth.get("lighting", "")),
                  frames=tuple(frames), truth=truth)
