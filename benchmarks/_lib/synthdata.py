"""Rendered drives for the benchmarks: frames in memory, and ``ficap synth`` bags kept in a cache.

A cached bag is named by everything that makes it (resolution, frames, fps, seed, the renderer's
``RENDER_VERSION``); bags are written atomically, so a run that stops half-way leaves nothing a
later run would take for a finished bag.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.transform import Transform
from ficap_ros.tools.synth import (
    RENDER_VERSION,
    RenderConfig,
    default_scene,
    naturalistic_drive,
    render,
)

FRAME_NS = 33_333_333  # 30 fps


@dataclass(frozen=True)
class SynthFrame:
    """One rendered frame: the image, its JPEG (q95, as ``ficap synth`` stores it) and its truth."""

    index: int
    stamp_ns: int
    image: np.ndarray
    jpeg: np.ndarray
    T_cam_cap: Transform
    visible_ids: frozenset[int]  # tags at least 99.9 % visible in the render
    front_ids: frozenset[int]  # tags on a front-facing face (a detection elsewhere is false)
    corners_px: dict[int, np.ndarray]


def encode_jpeg(image: np.ndarray, quality: int = 95) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf


def drive_frames(resolution: str, n: int, step: int = 1, start: int = 0, seed: int = 0,
                 config: RenderConfig | None = None, frontal_s: float | None = None
                 ) -> tuple[CameraModel, Iterator[SynthFrame]]:
    """The camera and ``n`` frames of a 30 fps naturalistic drive (seed ``seed``), every ``step``-th
    from frame ``start``, rendered with ``config`` (default: the realistic chain) as they are
    consumed."""
    model = nominal_model()
    scene = default_scene(resolution)
    kwargs = {} if frontal_s is None else {"frontal_s": frontal_s}
    drive = naturalistic_drive(start + n * step, fps=30.0, seed=seed, scene=scene, **kwargs)[start::step][:n]
    cfg = config or RenderConfig()

    def frames() -> Iterator[SynthFrame]:
        for d in drive:
            f = render(model, scene.camera, d.T_cam_cap, cfg, seed=d.index)
            yield SynthFrame(d.index, d.stamp_ns, f.image, encode_jpeg(f.image), d.T_cam_cap,
                             frozenset(f.visible_ids(0.999)), frozenset(f.corners_px), dict(f.corners_px))

    return scene.camera, frames()


def cached_synth_bag(cache: Path, resolution: str, frames: int, seed: int = 0, fps: float = 30.0,
                     extra: tuple[str, ...] = ()) -> Path:
    """A ``ficap synth`` bag in ``cache`` (rendered by the command on first use)."""
    tag = "_".join(a.strip("-").replace("=", "") for a in extra)
    name = f"synth_{resolution}_{frames}f_{fps:g}fps_s{seed}{'_' + tag if tag else ''}_r{RENDER_VERSION}"
    path = cache / name
    if (path / "metadata.yaml").is_file():
        return path
    cache.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(path, ignore_errors=True)  # an unfinished folder (the command writes atomically)
    subprocess.run([sys.executable, "-m", "ficap_ros.cli", "synth", "--out", str(path), "--resolution",
                    resolution, "--frames", str(frames), "--fps", str(fps), "--seed", str(seed), "--quiet",
                    *extra], check=True)
    return path


def looped_bag(cache: Path, source: Path, times: int) -> Path:
    """A bag of ``source``'s compressed images (with their CameraInfo) played ``times`` over, the
    stamps running on at the source's frame interval: a longer drive made of one short recording
    (each loop starts with a jump of the head, as after a cut)."""
    from ficap_ros.io import messages
    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.io.messages import ROSBAGS
    from ficap_ros.io.sources import CAMERA_INFO_TYPE, COMPRESSED_TYPE, open_frames

    name = f"{source.name}_x{times}"
    path = cache / name
    if (path / "metadata.yaml").is_file():
        return path
    raws = [r for r in open_frames(source).raw_frames() if r.kind == "compressed" and not r.error]
    if len(raws) < 2:
        raise RuntimeError(f"{source}: fewer than 2 compressed images")
    step = int(np.median(np.diff([r.stamp_ns for r in raws])))
    span = raws[-1].stamp_ns - raws[0].stamp_ns + step
    shutil.rmtree(path, ignore_errors=True)
    with BagWriter(path, storage="mcap", layout="folder") as bag:  # written atomically
        bag.add_topic("/camera/image_raw/compressed", COMPRESSED_TYPE)
        bag.add_topic("/camera/camera_info", CAMERA_INFO_TYPE)
        for k in range(times):
            for r in raws:
                stamp = r.stamp_ns + k * span
                head = messages.header(ROSBAGS, stamp, r.frame_id or "camera")
                bag.write("/camera/camera_info", stamp, messages.camera_info(ROSBAGS, head, r.camera))
                bag.write("/camera/image_raw/compressed", stamp,
                          messages.compressed_image(ROSBAGS, head, bytes(r.payload), r.encoding or "jpeg"))
    return path


def searched_bag(cache: Path, name: str, sources: list[Path], times: int, every: int = 1,
                 gap_ns: int = 2_000_000_000) -> Path:
    """A bag of every ``every``-th compressed image of each of ``sources`` (with its CameraInfo),
    the sources one after another, played ``times`` over, consecutive frames ``gap_ns`` apart:
    beyond tracking's reach, so every frame is searched over the whole image (as after a cut, a
    gap or dropped frames)."""
    from ficap_ros.io import messages
    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.io.messages import ROSBAGS
    from ficap_ros.io.sources import CAMERA_INFO_TYPE, COMPRESSED_TYPE, open_frames

    path = cache / f"{name}_x{times}"
    if (path / "metadata.yaml").is_file():
        return path
    raws = [r for src in sources
            for r in [r for r in open_frames(src).raw_frames() if r.kind == "compressed" and not r.error][::every]]
    if not raws:
        raise RuntimeError(f"{name}: no compressed images in {sources}")
    shutil.rmtree(path, ignore_errors=True)
    stamp = raws[0].stamp_ns
    with BagWriter(path, storage="mcap", layout="folder") as bag:  # written atomically
        bag.add_topic("/camera/image_raw/compressed", COMPRESSED_TYPE)
        bag.add_topic("/camera/camera_info", CAMERA_INFO_TYPE)
        for _ in range(times):
            for r in raws:
                head = messages.header(ROSBAGS, stamp, r.frame_id or "camera")
                bag.write("/camera/camera_info", stamp, messages.camera_info(ROSBAGS, head, r.camera))
                bag.write("/camera/image_raw/compressed", stamp,
                          messages.compressed_image(ROSBAGS, head, bytes(r.payload), r.encoding or "jpeg"))
                stamp += gap_ns
    return path
