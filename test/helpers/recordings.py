"""Recordings the command-line and reader tests share, and checks of what a verb prints.

The session fixtures of test/conftest.py (``drive``, ``replayed``, ``replayed_calibrated``,
``rendered_frames``, ``bag_with_a_corrupt_frame``) are built from the constants here; the helpers
cut a recording, write a small bag of noise, read a synth bag's truth and check a verb's error.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.sources import CAMERA_INFO_TYPE, IMAGE_TYPE

#: Frames and frame rate of the ``drive`` fixture: 9 s of drive, the 3 s frontal segment, then
#: mirror and cluster glances.
FRAMES = 45
FPS = 5.0
#: The ``glance_rs_drive`` fixture: 30 frames at 30 fps of a glance drive (0.2 s looking ahead,
#: then a right-mirror glance peaking near 240 deg/s), seed 11, through a rolling shutter reading
#: its rows top to bottom over 20 ms, each exposed 8 ms with motion blur.
RS_FRAMES = 30
RS_SEED = 11
RS_READOUT_MS = 20.0
RS_EXPOSURE_MS = 8.0
#: Frames of ``bag_with_a_corrupt_frame``, and the one whose JPEG is cut short.
CORRUPT_BAG_FRAMES = 5
CORRUPT_FRAME = 2


def one_error_line(capsys: pytest.CaptureFixture[str]) -> str:
    """The one line a verb printed on stderr (``ficap: error: ...``); fails on anything else."""
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ficap: error:"), err
    return err[0]


def digest(path: Path) -> dict[str, str]:
    """SHA-256 of every file of a folder (by relative path), or of one file (by name)."""
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    return {str(p.relative_to(path) if path.is_dir() else p.name):
            hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def cut_copy(drive: Path, dst: Path, fraction: float) -> Path:
    """A copy of a bag folder whose .mcap file is cut after ``fraction`` of its bytes."""
    shutil.copytree(drive, dst)
    data = next(dst.glob("*.mcap"))
    data.write_bytes(data.read_bytes()[: int(data.stat().st_size * fraction)])
    return dst


def small_bag(path: Path, storage: str, n: int = 40) -> list[np.ndarray]:
    """A bag of ``n`` 64x48 mono8 noise images at 30 fps with a CameraInfo each; the images."""
    cam = CameraModel.pinhole(64, 48, f_px=50.0)
    images = [np.random.default_rng(i).integers(0, 256, (48, 64), dtype=np.uint8)
              for i in range(n)]
    with BagWriter(path, storage=storage) as w:
        w.add_topic("/cam/image_raw", IMAGE_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        for i, img in enumerate(images):
            stamp = 1_700_000_000_000_000_000 + i * 33_333_333
            head = messages.header(ROSBAGS, stamp, "cam")
            w.write("/cam/camera_info", stamp, messages.camera_info(ROSBAGS, head, cam))
            w.write("/cam/image_raw", stamp, messages.image(ROSBAGS, head, img, "mono8"))
    return images


def true_R_cap_head(bag: Path) -> Rotation:
    """How the cap sits on the head in a synth bag (its metadata's ``ficap.R_cap_head_q_wxyz``)."""
    import yaml

    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    w, x, y, z = json.loads(meta["custom_data"]["ficap.R_cap_head_q_wxyz"])
    return Rotation.from_quat([x, y, z, w])
