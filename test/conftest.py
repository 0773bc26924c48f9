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

import pytest  # noqa: E402

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


# Property tests (hypothesis): derandomized, so a failure reproduces on every run and
# machine; no example database written into the checkout; no deadline on a shared 2-core box.
from hypothesis import settings as _hypothesis_settings  # noqa: E402

_hypothesis_settings.register_profile("ficap", max_examples=80, deadline=None, database=None,
                                      derandomize=True)
_hypothesis_settings.load_profile("ficap")
