"""ficap replay over a fleet: layout, fingerprints and skipping, and a local Ray (2 CPUs)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ficap_ros.cli.main import main
from ficap_ros.errors import BagError
from ficap_ros.tools import replay as replay_mod
from ficap_ros.tools.fleet import (
    Recording,
    find_recordings,
    fingerprint,
    input_identity,
)

FRAMES = 20
#: Segments of 8 frames, so 20-frame recordings span three segments (two full, one short) and
#: the Ray engine must put them back in order; set in this process, where segments are cut.
SEGMENT = 8


@pytest.fixture(scope="module")
def fleet_in(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three small synth recordings under a tree: two bag folders and a truncated .mcap file."""
    root = tmp_path_factory.mktemp("fleet") / "drives"
    for seed, rel in ((1, "alice/d1"), (2, "bob/d2"), (3, "bob/d3")):
        assert main(["synth", "--out", str(root / rel), "--resolution", "480x270", "--frames",
                     str(FRAMES), "--fps", "10", "--seed", str(seed), "--quiet"]) == 0
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
    monkeypatch.setattr(replay_mod, "SEGMENT_FRAMES", SEGMENT)


def _tcp_sockets() -> dict[int, tuple[str, str]]:
    """socket inode -> (local, remote) hex addresses, from /proc/net/tcp and tcp6."""
    out = {}
    for name in ("tcp", "tcp6"):
        for line in Path(f"/proc/net/{name}").read_text().splitlines()[1:]:
            parts = line.split()
            out[int(parts[9])] = (parts[1].split(":")[0], parts[2].split(":")[0])
    return out


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    seen, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for c in children.get(p, []):
            if c not in seen:
                seen.add(c)
                todo.append(c)
    return seen


def _is_loopback(hex_addr: str) -> bool:
    if len(hex_addr) == 8:  # IPv4, little-endian bytes: 127.x.x.x has 0x7F last
        return hex_addr[6:8] == "7F" or hex_addr == "00000000"
    # IPv6: ::1, :: (unbound), or ::ffff:127.x.x.x
    return hex_addr in ("00000000000000000000000001000000", "0" * 32) or (
        hex_addr[:24] == "0000000000000000FFFF0000" and hex_addr[30:32] == "7F")


@pytest.fixture(scope="module")
def local_ray():
    """The embedded Ray of ``--ray`` (2 CPUs), shared by this module's runs and shut down after."""
    pytest.importorskip("ray")
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.tools.fleet import RayEngine
    from ficap_ros.vision.pose import PoseConfig

    engine = RayEngine(nominal_model(), PoseConfig(), num_cpus=2)
    yield engine
    engine.close()


def test_ray_stays_on_loopback(local_ray) -> None:
    assert local_ray.cpus == 2
    sockets = _tcp_sockets()
    inodes = set()
    pids = _descendants(os.getpid()) | {os.getpid()}
    for pid in pids:
        try:
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                target = os.readlink(fd)
                if target.startswith("socket:["):
                    inodes.add(int(target[8:-1]))
        except OSError:
            continue
    ray_sockets = [sockets[i] for i in inodes if i in sockets]
    assert len(ray_sockets) >= 4  # the GCS, raylet and workers talk over TCP
    outside = [s for s in ray_sockets if not (_is_loopback(s[0]) and _is_loopback(s[1]))]
    assert not outside, f"Ray sockets off loopback: {outside}"


def test_ray_fleet_identical_resumable_and_reports_damage(
    fleet_in: Path, tmp_path: Path, local_ray, small_segments, capsys: pytest.CaptureFixture
) -> None:
    # Single-process references, recording by recording (the same segment length).
    refs = {}
    for rel in ("alice/d1", "bob/d2"):
        refs[rel] = tmp_path / "ref" / rel
        assert main(["replay", str(fleet_in / rel), "--out", str(refs[rel]), "--quiet"]) == 0
    cut_ref = tmp_path / "ref" / "cut"
    assert main(["replay", str(fleet_in / "bob/cut.mcap"), "--out", str(cut_ref), "--quiet"]) == 3
    out = tmp_path / "out"
    args = ["replay", str(fleet_in), "--out", str(out), "--ray", "--jobs", "2", "--quiet"]
    # The cut recording yields its frames before the cut (issue 13's recovery): "damaged", and
    # the fleet exits 3 as a single replay of it would.
    assert main(args) == 3
    printed = capsys.readouterr().out
    assert "bob/cut: damaged: " in printed and "2 done" in printed
    for rel, ref in refs.items():
        for name in ("labels.csv", "labels.mcap"):
            assert (out / rel / name).read_bytes() == (ref / name).read_bytes(), (rel, name)
        summary = json.loads((out / rel / "summary.json").read_text())
        assert summary["frames"] == FRAMES
        assert summary["fingerprint"]["settings"]["segment_frames"] == SEGMENT
    doc = json.loads((out / "fleet_summary.json").read_text())
    rows = {r["rel"]: r for r in doc["recordings"]}
    assert set(rows) == {"alice/d1", "bob/d2", "bob/cut"}
    assert rows["alice/d1"]["status"] == rows["bob/d2"]["status"] == "done"
    assert rows["alice/d1"]["frames"] == FRAMES and rows["alice/d1"]["pct_with_pose"] == 100.0
    assert 0.5 < rows["alice/d1"]["reliability_mean"] <= 1.0
    assert rows["bob/cut"]["status"] == "damaged"
    # What was recovered is labelled exactly as a single replay of the cut file labels it.
    for name in ("labels.csv", "labels.mcap"):
        assert (out / "bob/cut" / name).read_bytes() == (cut_ref / name).read_bytes(), name
    assert 0 < rows["bob/cut"]["frames"] < FRAMES and rows["bob/cut"]["frames_lost"] > 0
    assert doc["fleet"]["engine"] == "ray" and doc["fleet"]["workers"] == 2
    assert doc["fleet"]["frames_processed"] == 2 * FRAMES + rows["bob/cut"]["frames"]
    csv_lines = (out / "fleet_summary.csv").read_text().splitlines()
    assert len(csv_lines) == 4 and csv_lines[0].startswith("recording,rel,status,frames")
    assert (out / "fleet_summary.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # Second run: the finished recordings are current and skipped (untouched).
    mtimes = {rel: (out / rel / "labels.mcap").stat().st_mtime_ns for rel in refs}
    # (A current damaged recording is skipped too, so this re-run exits 0.)
    assert main(args) == 0
    doc = json.loads((out / "fleet_summary.json").read_text())
    assert sorted(r["status"] for r in doc["recordings"]) == ["skipped", "skipped", "skipped"]
    assert all((out / rel / "labels.mcap").stat().st_mtime_ns == t for rel, t in mtimes.items())

    # --force redoes them, with the same bytes.
    assert main(args + ["--force"]) == 3
    doc = json.loads((out / "fleet_summary.json").read_text())
    assert sorted(r["status"] for r in doc["recordings"]) == ["damaged", "done", "done"]
    for rel, ref in refs.items():
        assert (out / rel / "labels.mcap").stat().st_mtime_ns != mtimes[rel]
        assert (out / rel / "labels.csv").read_bytes() == (ref / "labels.csv").read_bytes()


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
    assert summary["method"] == "paper" and summary["fingerprint"]["settings"]["pose"].count("paper")


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
    assert "edge_photometric=True" in settings["detector"]
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


def test_layout_mirrors_inputs_and_manifest(fleet_in: Path, tmp_path: Path) -> None:
    one_tree = find_recordings([fleet_in])
    assert {str(r.rel) for r in one_tree} == {"alice/d1", "bob/d2", "bob/cut"}
    assert {r.path for r in one_tree} == {fleet_in / "alice/d1", fleet_in / "bob/d2",
                                          fleet_in / "bob/cut.mcap"}
    two = find_recordings([fleet_in / "alice", fleet_in / "bob/cut.mcap"])
    assert [str(r.rel) for r in two] == ["alice/d1", "cut"]
    assert find_recordings([fleet_in / "alice/d1"]) == [Recording(fleet_in / "alice/d1", Path("."))]
    manifest = fleet_in / "fleet.txt"
    manifest.write_text("# the drives\nalice/d1\n\nbob/cut.mcap  # truncated\n")
    try:
        got = find_recordings([], manifest)
    finally:
        manifest.unlink()
    assert [(r.path, str(r.rel)) for r in got] == [(fleet_in / "alice/d1", "alice/d1"),
                                                   (fleet_in / "bob/cut.mcap", "bob/cut")]
    # Outputs written inside the searched tree are not taken for recordings.
    out = fleet_in / "labels_out"
    (out / "x").mkdir(parents=True)
    (out / "x" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    try:
        assert len(find_recordings([fleet_in], out=out)) == 3
    finally:
        (out / "x" / "metadata.yaml").unlink()
        (out / "x").rmdir()
        out.rmdir()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "cut.mcap").write_bytes(b"\x89MCAP0\r\n")
    with pytest.raises(BagError, match="would both write"):
        find_recordings([fleet_in / "bob/cut.mcap", tmp_path / "other" / "cut.mcap"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(BagError, match="no recording"):
        find_recordings([tmp_path / "empty"])
    with pytest.raises(BagError, match="does not exist"):
        find_recordings([tmp_path / "nope"])


def test_fingerprint_follows_the_input_not_its_place(fleet_in: Path, tmp_path: Path) -> None:
    settings = {"method": "joint"}
    a = fingerprint(fleet_in / "alice/d1", settings)
    copy = tmp_path / "d1"
    copy.mkdir()
    for f in (fleet_in / "alice/d1").iterdir():
        (copy / f.name).write_bytes(f.read_bytes())
    assert fingerprint(copy, settings)["sha256"] == a["sha256"]  # a copied fleet still resumes
    mcap = next(copy.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    data[-100] ^= 0xFF
    mcap.write_bytes(bytes(data))
    assert fingerprint(copy, settings)["sha256"] != a["sha256"]
    assert fingerprint(fleet_in / "alice/d1", {"method": "paper"})["sha256"] != a["sha256"]
    assert set(input_identity(copy)["files"]) == {mcap.name, "metadata.yaml"}


def test_no_ray_import_without_ray(fleet_in: Path, tmp_path: Path) -> None:
    code = ("import sys; from ficap_ros.cli.main import main; "
            f"rc = main(['replay', {str(fleet_in / 'alice/d1')!r}, {str(fleet_in / 'bob/d2')!r}, "
            f"'--out', {str(tmp_path / 'o')!r}, '--quiet']); "
            "assert rc == 0, rc; assert 'ray' not in sys.modules, 'ray imported'; print('ok')")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().endswith("ok")


def test_ray_retries_a_dead_worker_and_fails_only_the_broken_recording(
    fleet_in: Path, tmp_path: Path, local_ray, small_segments
) -> None:
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io.sources import open_frames
    from ficap_ros.tools.fleet import RayEngine, label_settings, run_fleet
    from ficap_ros.vision.pose import PoseConfig

    model, pose = nominal_model(), PoseConfig()
    recs = [Recording(fleet_in / "alice/d1", Path("d1")), Recording(fleet_in / "bob/d2", Path("d2"))]
    ref = tmp_path / "ref"
    assert main(["replay", str(recs[0].path), "--out", str(ref), "--quiet"]) == 0
    settings = label_settings(model, pose)

    # A worker process that dies on its first task: Ray re-runs the segment, the labels are whole.
    marker = str(tmp_path / "died")

    def dies_once(config, raws):  # runs in a Ray worker (pickled by value)
        import os as _os
        from pathlib import Path as _Path

        from ficap_ros.tools.fleet import _ray_segment

        if not _Path(marker).exists():
            _Path(marker).touch()
            _os._exit(1)
        return _ray_segment(config, raws)

    engine = RayEngine(model, pose, retries=2, segment_fn=dies_once)
    fleet = run_fleet(recs[:1], tmp_path / "retried", open_frames, model, pose, settings,
                      progress=False, ray_engine=engine)
    assert Path(marker).exists() and [r.status for r in fleet.results] == ["done"]
    for name in ("labels.csv", "labels.mcap"):
        assert (tmp_path / "retried/d1" / name).read_bytes() == (ref / name).read_bytes()

    # A segment whose processing raises (not a dead worker: no retry) fails its recording only.
    poison = next(iter(open_frames(recs[1].path).raw_frames())).payload

    def breaks_on_d2(config, raws):
        from ficap_ros.tools.fleet import _ray_segment

        if any(r.payload == poison for r in raws):
            raise RuntimeError("pipeline bug on this segment")
        return _ray_segment(config, raws)

    engine = RayEngine(model, pose, retries=2, segment_fn=breaks_on_d2)
    fleet = run_fleet(recs, tmp_path / "isolated", open_frames, model, pose, settings,
                      progress=False, ray_engine=engine)
    by_rel = {r.rel: r for r in fleet.results}
    assert by_rel["d1"].status == "done" and by_rel["d1"].frames == FRAMES
    assert by_rel["d2"].status == "failed" and "pipeline bug on this segment" in by_rel["d2"].error
    assert (tmp_path / "isolated/d1/labels.csv").read_bytes() == (ref / "labels.csv").read_bytes()
    assert not (tmp_path / "isolated/d2/summary.json").exists()

    # An engine started with other settings than the fleet's would write labels its fingerprints
    # do not describe: refused before anything is written.
    from ficap_ros.errors import ConfigError
    from ficap_ros.vision.detector import DetectorConfig

    for other in ({"pose": PoseConfig(method="paper")}, {"detector": DetectorConfig(edge_photometric=True)}):
        with pytest.raises(ConfigError, match="another model, pose or detector"):
            run_fleet(recs[:1], tmp_path / "mismatch", open_frames, model, other.get("pose", pose),
                      settings, progress=False, ray_engine=engine, detector=other.get("detector"))
    assert not (tmp_path / "mismatch" / "d1").exists()


def test_unreachable_cluster_is_one_line(fleet_in: Path, tmp_path: Path, capsys) -> None:
    """--ray-address that nothing answers: a one-line error at once (ray.init would retry for
    minutes), and nothing written."""
    import socket

    with socket.socket() as s:  # a loopback port that was free a moment ago
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    rc = main(["replay", str(fleet_in / "alice/d1"), "--out", str(tmp_path / "o"),
               "--ray-address", f"127.0.0.1:{port}", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 1 and f"no Ray cluster answers at 127.0.0.1:{port}" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o" / "labels.csv").exists()
