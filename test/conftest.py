"""Shared fixtures. Every test process keeps DDS on loopback and gets its own ROS domain."""

from __future__ import annotations

import os

# Set before any test imports rclpy: loopback only, and a ROS_DOMAIN_ID per xdist worker so tests
# that run at once never see each other's topics. FICAP_TEST_DOMAIN_BASE moves the whole block, so
# two test runs on one machine (two checkouts) can run at the same time.
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
_worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
_base = int(os.environ.get("FICAP_TEST_DOMAIN_BASE", "60"))
os.environ["ROS_DOMAIN_ID"] = str(_base + int(_worker.lstrip("gw") or 0))

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

#: Real photos the detection tests need, kept in the repository (test/data/README.md: sources and
#: licences) so a fresh clone tests without the workplace's ../shared; benchmarks read the full sets.
REAL_APRILTAG = Path(__file__).resolve().parent / "data" / "real_apriltag"


@pytest.fixture(scope="session")
def real_apriltag_dir() -> Path:
    assert REAL_APRILTAG.is_dir(), f"test photos missing at {REAL_APRILTAG}"
    return REAL_APRILTAG


# Property tests (test_fuzz_readers.py): derandomized, so a failure reproduces on every run and
# machine; no example database written into the checkout; no deadline on a shared 2-core box.
from hypothesis import settings as _hypothesis_settings  # noqa: E402

_hypothesis_settings.register_profile("ficap", max_examples=80, deadline=None, database=None,
                                      derandomize=True)
_hypothesis_settings.load_profile("ficap")
