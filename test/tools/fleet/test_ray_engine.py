"""ficap_ros.tools.fleet.ray_engine: a local Ray (2 CPUs) on loopback, labels identical to one
process, a dead worker retried, a broken segment failing its recording only."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from fleet_inputs import FLEET_FRAMES as FRAMES
from fleet_inputs import FLEET_SEGMENT as SEGMENT

from ficap_ros.cli.main import main
from ficap_ros.tools.fleet.manifest import Recording


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
    from ficap_ros.tools.fleet.ray_engine import RayEngine
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
    # The cut recording yields its frames before the cut (io.salvage): "damaged", and
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


def test_ray_retries_a_dead_worker_and_fails_only_the_broken_recording(
    fleet_in: Path, tmp_path: Path, local_ray, small_segments
) -> None:
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io.sources import open_frames
    from ficap_ros.tools.fleet.fingerprints import label_settings
    from ficap_ros.tools.fleet.ray_engine import RayEngine
    from ficap_ros.tools.fleet.run import run_fleet
    from ficap_ros.vision.pose import PoseConfig

    model, pose = nominal_model(), PoseConfig()
    recs = [Recording(fleet_in / "alice/d1", Path("d1")), Recording(fleet_in / "bob/d2", Path("d2"))]
    ref = tmp_path / "ref"
    assert main(["replay", str(recs[0].path), "--out", str(ref), "--quiet"]) == 0
    settings = label_settings(model, pose)

    # A worker process that dies on its first task: Ray re-runs the segment, the labels are whole.
    marker = str(tmp_path / "died")

    def dies_once(config, raws, timing):  # runs in a Ray worker (pickled by value)
        import os as _os
        from pathlib import Path as _Path

        from ficap_ros.tools.fleet.ray_engine import ray_segment

        if not _Path(marker).exists():
            _Path(marker).touch()
            _os._exit(1)
        return ray_segment(config, raws, timing)

    engine = RayEngine(model, pose, retries=2, segment_fn=dies_once)
    fleet = run_fleet(recs[:1], tmp_path / "retried", open_frames, model, pose, settings,
                      progress=False, ray_engine=engine)
    assert Path(marker).exists() and [r.status for r in fleet.results] == ["done"]
    for name in ("labels.csv", "labels.mcap"):
        assert (tmp_path / "retried/d1" / name).read_bytes() == (ref / name).read_bytes()

    # A segment whose processing raises (not a dead worker: no retry) fails its recording only.
    poison = next(iter(open_frames(recs[1].path).raw_frames())).payload

    def breaks_on_d2(config, raws, timing):
        from ficap_ros.tools.fleet.ray_engine import ray_segment

        if any(r.payload == poison for r in raws):
            raise RuntimeError("pipeline bug on this segment")
        return ray_segment(config, raws, timing)

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


def test_workers_that_cannot_start_fail_within_the_stated_time(local_ray) -> None:
    """No worker ever runs the engine's first task (here: it asks for a resource no node has,
    as a task waits when its workers cannot start): one line within the start timeout, not a
    fleet that waits at 0 frames."""
    import time

    from ficap_ros.errors import WorkerError
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.tools.fleet.ray_engine import START_TIMEOUT_S, RayEngine
    from ficap_ros.vision.pose import PoseConfig

    assert START_TIMEOUT_S <= 120.0  # the stated bound of a real run
    t0 = time.monotonic()
    with pytest.raises(WorkerError, match=r"no Ray worker started within 2 s \(2 CPUs\)") as info:
        RayEngine(nominal_model(), PoseConfig(), start_timeout_s=2.0,
                  task_options={"resources": {"nowhere": 1}})
    assert time.monotonic() - t0 < 15.0 and "\n" not in str(info.value)
    assert local_ray.cpus == 2  # the shared Ray is left running
