"""ficap_ros.tools.fleet.run: a fleet replayed with processes: skipping what is current, redoing
what changed or was cut off, ``--photometric`` reaching every recording, no ray imported."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from ficap_ros.cli.main import main


def test_changed_settings_redo_a_recording(fleet_in: Path, tmp_path: Path) -> None:
    """The fingerprint holds every label-changing setting: --method paper is not skipped."""
    out = tmp_path / "out"
    rec = str(fleet_in / "alice/d1")
    base = ["replay", rec, str(fleet_in / "bob/d2"), "--out", str(out), "--quiet"]
    assert main(base) == 0
    assert main(base) == 0
    doc = json.loads((out / "fleet_summary.json").read_text())
    assert [r["status"] for r in doc["recordings"]] == ["skipped", "skipped"]
    assert main(base + ["--method", "paper"]) == 0
    doc = json.loads((out / "fleet_summary.json").read_text())
    assert [r["status"] for r in doc["recordings"]] == ["done", "done"]
    summary = json.loads((out / "d1" / "summary.json").read_text())
    assert summary["method"] == "paper" and summary["fingerprint"]["settings"]["pose"]["method"] == "paper"


def test_photometric_fleet_matches_a_single_photometric_replay(fleet_in: Path, tmp_path: Path) -> None:
    """--photometric reaches every recording of a fleet and its fingerprint: the default run's
    outputs are redone, and each recording's labels are the single-recording --photometric ones."""
    out = tmp_path / "out"
    recs = [str(fleet_in / "alice/d1"), str(fleet_in / "bob/d2")]
    assert main(["replay", *recs, "--out", str(out), "--quiet"]) == 0
    default = (out / "d1" / "labels.csv").read_text()
    assert "photometric" not in json.loads((out / "d1" / "summary.json").read_text())  # as before
    assert main(["replay", *recs, "--out", str(out), "--quiet", "--photometric"]) == 0
    doc = json.loads((out / "fleet_summary.json").read_text())
    assert [r["status"] for r in doc["recordings"]] == ["done", "done"]
    settings = json.loads((out / "d1" / "summary.json").read_text())["fingerprint"]["settings"]
    assert settings["detector"]["edge_photometric"] is True
    single = tmp_path / "single"
    assert main(["replay", recs[0], "--out", str(single), "--quiet", "--photometric"]) == 0
    assert (out / "d1" / "labels.csv").read_text() == (single / "labels.csv").read_text() != default
    # summary.json says how the labels were made: the single replay's too (it has no fingerprint).
    assert json.loads((single / "summary.json").read_text())["photometric"] is True
    assert json.loads((out / "d1" / "summary.json").read_text())["photometric"] is True
    assert main(["replay", *recs, "--out", str(out), "--quiet", "--photometric"]) == 0
    doc = json.loads((out / "fleet_summary.json").read_text())
    assert [r["status"] for r in doc["recordings"]] == ["skipped", "skipped"]


def test_interrupted_recording_is_redone(fleet_in: Path, tmp_path: Path) -> None:
    """Outputs without their summary.json (a run killed while writing) are not current."""
    out = tmp_path / "out"
    base = ["replay", str(fleet_in / "alice/d1"), str(fleet_in / "bob/d2"), "--out", str(out), "--quiet"]
    assert main(base) == 0
    (out / "d2" / "summary.json").unlink()
    assert main(base) == 0
    doc = json.loads((out / "fleet_summary.json").read_text())
    assert [r["status"] for r in doc["recordings"]] == ["skipped", "done"]


def test_no_ray_import_without_ray(fleet_in: Path, tmp_path: Path) -> None:
    code = ("import sys; from ficap_ros.cli.main import main; "
            f"rc = main(['replay', {str(fleet_in / 'alice/d1')!r}, {str(fleet_in / 'bob/d2')!r}, "
            f"'--out', {str(tmp_path / 'o')!r}, '--quiet']); "
            "assert rc == 0, rc; assert 'ray' not in sys.modules, 'ray imported'; print('ok')")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().endswith("ok")


def test_a_fleet_whose_workers_keep_dying_fails_them_and_ends(fleet_in: Path, tmp_path: Path,
                                                              capsys) -> None:  # noqa: ANN001
    """Without Ray, --jobs 2 workers killed as they start: each recording fails in one line
    (its segment's workers died twice), the fleet ends and says so; nothing waits for ever."""
    import threading
    import time

    from probe_cases import kill_pool_workers

    from ficap_ros.tools.replay import available_cores

    if available_cores() < 2:
        import pytest

        pytest.skip("--jobs 2 needs two cores")
    stop, killed = threading.Event(), []
    killer = threading.Thread(target=kill_pool_workers, args=(stop, 100, killed), daemon=True)
    killer.start()
    t0 = time.monotonic()
    try:
        code = main(["replay", str(fleet_in / "alice/d1"), str(fleet_in / "bob/d2"), "--out",
                     str(tmp_path / "out"), "--jobs", "2", "--quiet"])
    finally:
        stop.set()
        killer.join(timeout=10)
    out = capsys.readouterr().out.splitlines()
    assert code == 1 and time.monotonic() - t0 < 120.0
    failed = [line for line in out if ": failed: a worker process died twice on frames 0-" in line]
    assert len(failed) == 2, out
    assert out[-1].startswith("2 recordings: 0 done, 0 skipped (current), 0 damaged, 2 failed")


def test_a_fleet_whose_worker_is_killed_once_finishes_with_the_same_labels(
        fleet_in: Path, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """Without Ray, --jobs 2 with one worker killed (SIGKILL) mid-run: its segment runs again in
    a new pool, every recording is done, and the labels are those of --jobs 1."""
    import threading
    import time

    import pytest
    from probe_cases import kill_pool_workers

    from ficap_ros.tools.replay import available_cores

    if available_cores() < 2:
        pytest.skip("--jobs 2 needs two cores")
    recs = [str(fleet_in / "alice/d1"), str(fleet_in / "bob/d2")]
    assert main(["replay", *recs, "--out", str(tmp_path / "one"), "--quiet"]) == 0
    stop, killed = threading.Event(), []
    killer = threading.Thread(target=kill_pool_workers, args=(stop, 1, killed), daemon=True)
    killer.start()
    t0 = time.monotonic()
    try:
        code = main(["replay", *recs, "--out", str(tmp_path / "two"), "--jobs", "2", "--quiet"])
    finally:
        stop.set()
        killer.join(timeout=10)
    out = capsys.readouterr().out.splitlines()
    assert code == 0 and len(killed) == 1 and time.monotonic() - t0 < 120.0, out
    assert out[-1].startswith("2 recordings: 2 done, 0 skipped (current), 0 damaged, 0 failed")
    for name in ("d1", "d2"):
        assert (tmp_path / "two" / name / "labels.csv").read_bytes() == \
            (tmp_path / "one" / name / "labels.csv").read_bytes()
