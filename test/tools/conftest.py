"""Fixtures of the tools tests: a small fleet of synth recordings, and short replay segments."""

from __future__ import annotations

from pathlib import Path

import pytest
from fleet_inputs import FLEET_FRAMES, FLEET_SEGMENT

from ficap_ros.cli.main import main
from ficap_ros.tools import replay as replay_mod


@pytest.fixture(scope="session")
def fleet_in(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three small synth recordings under a tree: two bag folders and a truncated .mcap file."""
    root = tmp_path_factory.mktemp("fleet") / "drives"
    for seed, rel in ((1, "alice/d1"), (2, "bob/d2"), (3, "bob/d3")):
        assert main(["synth", "--out", str(root / rel), "--resolution", "480x270", "--frames",
                     str(FLEET_FRAMES), "--fps", "10", "--seed", str(seed), "--quiet"]) == 0
    # d3 becomes a lone .mcap cut at 60 %: what a recorder killed mid-drive leaves.
    whole = next((root / "bob/d3").glob("*.mcap"))
    data = whole.read_bytes()
    (root / "bob/cut.mcap").write_bytes(data[: len(data) * 6 // 10])
    for f in (root / "bob/d3").iterdir():
        f.unlink()
    (root / "bob/d3").rmdir()
    return root


@pytest.fixture
def small_segments(monkeypatch: pytest.MonkeyPatch) -> None:
    """Short replay segments, set in this process (where segments are cut)."""
    monkeypatch.setattr(replay_mod, "SEGMENT_FRAMES", FLEET_SEGMENT)
