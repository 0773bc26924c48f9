"""The options every benchmark script takes, and the environment it runs in."""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

#: The repository (benchmarks/_lib/ is two levels below it).
ROOT = Path(__file__).resolve().parents[2]


def default_data() -> Path:
    """``../shared/data`` next to the clone, or next to its parent (a git worktree one level further
    down); the first that exists, else the first candidate."""
    candidates = [ROOT.parent / "shared" / "data", ROOT.parent.parent / "shared" / "data"]
    return next((p for p in candidates if p.is_dir()), candidates[0])


def default_cache() -> Path:
    """Where rendered drives are kept between runs: ``$FICAP_BENCH_CACHE``, else
    ``$XDG_CACHE_HOME/ficap_bench``, else the system's temporary folder."""
    if os.environ.get("FICAP_BENCH_CACHE"):
        return Path(os.environ["FICAP_BENCH_CACHE"])
    if os.environ.get("XDG_CACHE_HOME"):
        return Path(os.environ["XDG_CACHE_HOME"]) / "ficap_bench"
    return Path(tempfile.gettempdir()) / "ficap_bench"


def parser(doc: str, quick: str) -> argparse.ArgumentParser:
    """A parser with the script's docstring as its help and the common options.

    ``quick`` says what ``--quick`` changes (every script takes it, so ``make bench
    BENCH_ARGS=--quick`` passes it to all)."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help=f"a fast run: {quick}")
    ap.add_argument("--data", type=Path, default=default_data(),
                    help="folder with blender_dev/ and real_apriltag/ (default: ../shared/data "
                         "relative to the repository)")
    ap.add_argument("--cache", type=Path, default=default_cache(),
                    help="folder for rendered drives kept between runs (default: $FICAP_BENCH_CACHE, "
                         "$XDG_CACHE_HOME/ficap_bench or the temporary folder)")
    ap.add_argument("--no-doc", action="store_true",
                    help="print the section only; do not write docs/benchmarks/")
    return ap


def ros_environment() -> dict[str, str]:
    """This process's environment with DDS kept on loopback; a caller's ROS_DOMAIN_ID is kept
    (70 when none is set). Also applied to ``os.environ`` so rclpy started here sees it."""
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.setdefault("ROS_DOMAIN_ID", "70")
    return dict(os.environ)
