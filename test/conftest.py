"""Shared fixtures. Every test process keeps DDS on loopback and gets its own ROS domain."""

from __future__ import annotations

import os

# Set before any test imports rclpy: DDS on loopback only, and one ROS domain per xdist worker so
# tests that run at once never see each other's topics. The domain a caller set (ROS_DOMAIN_ID) is
# kept as the first worker's and offset by one per further worker; unset, the block starts at 60.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
_worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").lstrip("gw") or 0)
os.environ["ROS_DOMAIN_ID"] = str(int(os.environ.get("ROS_DOMAIN_ID") or 60) + _worker)

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from recordings import (  # noqa: E402
    CORRUPT_BAG_FRAMES,
    CORRUPT_FRAME,
    FPS,
    FRAMES,
    RS_EXPOSURE_MS,
    RS_FRAMES,
    RS_READOUT_MS,
    RS_SEED,
)


def pytest_configure(config: pytest.Config) -> None:
    """The message packages the ROS wheels lack must be there (the tests see /tf, /tf_static and
    the detections on real DDS): one line saying how, not a collection traceback."""
    import importlib.util

    missing = [m for m in ("tf2_msgs", "apriltag_msgs") if importlib.util.find_spec(m) is None]
    if missing:
        raise pytest.UsageError(
            f"{' and '.join(missing)} not importable: `make` generates them into the venv "
            "(python scripts/build_ros_interfaces.py --venv <venv>); a ROS install has them "
            "(package.xml)")


def pytest_sessionstart(session: pytest.Session) -> None:
    """The compiled kernels (``ficap_ros.vision.jit``: the corner stage's and the photometric
    fit's) compiled, or loaded from their cache, once in the controlling process before any xdist
    worker starts: on a fresh clone every worker's detection, replay and node tests then load them
    instead of each compiling them."""
    if hasattr(session.config, "workerinput"):  # an xdist worker: its controller did it
        return
    from ficap_ros.vision.jit import warm_up

    warm_up()


#: Real photos the detection tests need, kept in the repository (test/data/README.md: sources and
#: licences) so a fresh clone tests without the workplace's ../shared; benchmarks read the full sets.
REAL_APRILTAG = Path(__file__).resolve().parent / "data" / "real_apriltag"


@pytest.fixture(scope="session")
def real_apriltag_dir() -> Path:
    assert REAL_APRILTAG.is_dir(), f"test photos missing at {REAL_APRILTAG}"
    return REAL_APRILTAG


@pytest.fixture(scope="session")
def mapping_photos(real_apriltag_dir: Path) -> tuple[Path, dict[str, set[int]]]:
    """The hand-labelled mapping photos kept in test/data: their folder and, per photo, the ids of
    the tags it shows (groundtruth.txt)."""
    root = real_apriltag_dir / "swatbotics_mapping_feb_2014"
    truth = {}
    for line in (root / "groundtruth.txt").read_text().splitlines():
        parts = line.split()
        if parts:
            truth[parts[0]] = set(map(int, parts[1:]))
    return root, truth


# -- recordings several test modules read (each built once per test process) ----------------------
@pytest.fixture(scope="session")
def drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A ``ficap synth`` drive: 540p, ``FRAMES`` frames at ``FPS`` (the 3 s frontal segment, then
    mirror and cluster glances), seed 3, with its exact truth topics."""
    from ficap_ros.cli.main import main

    bag = tmp_path_factory.mktemp("synth") / "drive"
    assert main(["synth", "--out", str(bag), "--resolution", "540p", "--frames", str(FRAMES),
                 "--fps", str(FPS), "--seed", "3", "--quiet"]) == 0
    return bag


@pytest.fixture(scope="session")
def glance_rs_drive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A ``ficap synth`` rolling-shutter glance drive (recordings.RS_*): 540p, the rows read top
    to bottom, each exposed with motion blur, the truth the pose at the stamp (the middle row's
    mid-exposure); its timing in the bag's metadata."""
    from ficap_ros.cli.main import main

    bag = tmp_path_factory.mktemp("synth_rs") / "glances"
    assert main(["synth", "--out", str(bag), "--resolution", "540p", "--frames", str(RS_FRAMES),
                 "--fps", "30", "--seed", str(RS_SEED), "--motion", "glances", "--frontal-s", "0.2",
                 "--readout-ms", str(RS_READOUT_MS), "--exposure-ms", str(RS_EXPOSURE_MS),
                 "--motion-blur", "--quiet"]) == 0
    return bag


@pytest.fixture(scope="session")
def replayed(drive: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``ficap replay`` of ``drive`` (uncalibrated): labels.mcap, labels.csv, summary.json."""
    from ficap_ros.cli.main import main

    out = tmp_path_factory.mktemp("replay") / "out"
    assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 0
    return out


@pytest.fixture(scope="session")
def replayed_calibrated(drive: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``ficap replay`` of ``drive`` calibrated on its first 2.9 s (looking straight ahead)."""
    from ficap_ros.cli.main import main

    out = tmp_path_factory.mktemp("replay_calibrated") / "out"
    assert main(["replay", str(drive), "--out", str(out), "--calibrate-frontal", "0:2.9",
                 "--quiet"]) == 0
    return out


@pytest.fixture(scope="session")
def rendered_frames():
    """``CORRUPT_BAG_FRAMES`` rendered 540p frames of a drive (seed 5) and their scene."""
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.tools import synth

    scene = synth.default_scene("540p")
    frames = synth.naturalistic_drive(CORRUPT_BAG_FRAMES, 30.0, 5, scene)
    model = nominal_model()
    return [synth.render(model, scene.camera, f.T_cam_cap, seed=f.index).image for f in frames], scene


@pytest.fixture(scope="session")
def bag_with_a_corrupt_frame(rendered_frames, tmp_path_factory: pytest.TempPathFactory) -> Path:  # noqa: ANN001
    """A single .mcap of ``rendered_frames`` as JPEG CompressedImage with CameraInfo, 30 fps;
    frame ``CORRUPT_FRAME``'s JPEG is cut short (undecodable)."""
    import cv2

    from ficap_ros.io import messages
    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.io.messages import ROSBAGS
    from ficap_ros.io.sources import CAMERA_INFO_TYPE, COMPRESSED_TYPE

    images, scene = rendered_frames
    path = tmp_path_factory.mktemp("bags") / "drive.mcap"
    with BagWriter(path, storage="mcap", layout="file") as w:
        w.add_topic("/cam/image/compressed", COMPRESSED_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        for i, img in enumerate(images):
            s = 1_700_000_000_000_000_000 + i * 33_333_333
            head = messages.header(ROSBAGS, s, "cam")
            w.write("/cam/camera_info", s, messages.camera_info(ROSBAGS, head, scene.camera))
            data = (cv2.imencode(".jpg", img)[1].tobytes() if i != CORRUPT_FRAME
                    else b"\xff\xd8 truncated")
            w.write("/cam/image/compressed", s, messages.compressed_image(ROSBAGS, head, data))
    return path


@pytest.fixture
def binary_files(tmp_path: Path) -> dict[str, Path]:
    """Files that are not text: random bytes (``bin``) and UTF-16 YAML (``utf16``)."""
    rng = np.random.default_rng(13)
    files = {"bin": tmp_path / "bin.yaml", "utf16": tmp_path / "utf16.yaml"}
    files["bin"].write_bytes(rng.integers(0, 256, 300, dtype=np.uint8).tobytes())
    files["utf16"].write_text("R_cap_head_q_wxyz: [1, 0, 0, 0]\n", encoding="utf-16")
    return files


# Property tests (hypothesis): derandomized, so a failure reproduces on every run and
# machine; no example database written into the checkout; no deadline on a shared 2-core box.
from hypothesis import settings as _hypothesis_settings  # noqa: E402

_hypothesis_settings.register_profile("ficap", max_examples=80, deadline=None, database=None,
                                      derandomize=True)
_hypothesis_settings.load_profile("ficap")
