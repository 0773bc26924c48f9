"""ficap_ros.tools.fleet.summary: a recording's line from its summary.json, and the fleet
summary files."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from ficap_ros.tools.fleet.manifest import Recording
from ficap_ros.tools.fleet.summary import (
    FLEET_FILES,
    FleetResult,
    RecordingResult,
    recording_result,
    write_fleet_summary,
)


def test_a_recording_line_counts_lost_frames_and_damage() -> None:
    rec = Recording(Path("/in/d1"), Path("a/d1"))
    whole = {"frames": 10, "frames_with_pose": 8, "pct_with_pose": 80.0, "pct_ge4_tags": 70.0,
             "frames_skipped": 1, "frames_lost": 0, "damaged": False}
    r = recording_result(rec, "done", whole, [0.5, 1.0, math.nan], 1.23456)
    assert (r.status, r.frames, r.frames_lost, r.wall_s) == ("done", 10, 1, 1.235)
    assert r.reliability_mean == 0.75 and r.reliability_median == 0.75  # NaN left out
    cut = {**whole, "frames_lost": 4, "damaged": True}
    r = recording_result(rec, "done", cut, [], 0.0)
    assert r.status == "damaged" and r.frames_lost == 5 and math.isnan(r.reliability_mean)
    assert recording_result(rec, "skipped", cut, [], 0.0).status == "skipped"


def test_fleet_summary_files(tmp_path: Path) -> None:
    fleet = FleetResult([RecordingResult("/in/d1", "d1", "done", 10, 8, 80.0, 70.0, 0.75, 0.8, 0, 2.0),
                         RecordingResult("/in/d2", "d2", "failed", error="cannot read")],
                        wall_s=4.0, engine="processes", workers=2)
    paths = write_fleet_summary(tmp_path, fleet)
    assert [p.name for p in paths] == list(FLEET_FILES)
    rows = list(csv.DictReader((tmp_path / "fleet_summary.csv").open()))
    assert [r["status"] for r in rows] == ["done", "failed"]
    assert rows[1]["reliability_mean"] == "" and rows[1]["error"] == "cannot read"  # NaN: empty
    doc = json.loads((tmp_path / "fleet_summary.json").read_text())
    assert doc["fleet"]["done"] == 1 and doc["fleet"]["failed"] == 1
    assert doc["fleet"]["frames_processed"] == 10 and doc["fleet"]["throughput_fps"] == 2.5
    assert doc["recordings"][1]["reliability_mean"] is None
    assert (tmp_path / "fleet_summary.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_an_unknown_loss_is_never_counted_as_zero(tmp_path: Path) -> None:
    """A damaged recording whose container cannot say how many frames it lost: damaged, its
    frames_lost unknown (empty in the CSV, counted apart in the totals), not '0 lost'."""
    import json

    from ficap_ros.tools.fleet.manifest import Recording
    from ficap_ros.tools.fleet.summary import (
        FleetResult,
        recording_result,
        write_fleet_summary,
    )

    summary = {"frames": 10, "frames_skipped": 0, "damaged": True, "frames_lost": None}
    r = recording_result(Recording(Path("a.mcap"), Path("a")), "done", summary, [0.9], 1.0)
    assert r.status == "damaged" and r.frames_lost is None
    write_fleet_summary(tmp_path, FleetResult([r], 1.0))
    rows = (tmp_path / "fleet_summary.csv").read_text().splitlines()
    assert rows[1].split(",")[rows[0].split(",").index("frames_lost")] == ""
    totals = json.loads((tmp_path / "fleet_summary.json").read_text())["fleet"]
    assert totals["frames_lost"] == 0 and totals["recordings_lost_unknown"] == 1
