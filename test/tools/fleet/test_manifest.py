"""ficap_ros.tools.fleet.manifest: which recordings a fleet holds and where their outputs go."""

from __future__ import annotations

from pathlib import Path

import pytest

from ficap_ros.errors import BagError
from ficap_ros.tools.fleet.manifest import (
    Recording,
    find_recordings,
    is_recording,
    read_manifest,
)


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


def test_manifest_entries_and_recordings(tmp_path: Path) -> None:
    """A manifest's relative entries mirror their paths, absolute ones take their names; bag
    folders and files are recordings, videos only when asked, replay outputs never."""
    manifest = tmp_path / "m.txt"
    manifest.write_text(f"a/b/drive.mcap\n  # a comment\n{tmp_path / 'x' / 'v.mp4'}  # abs\n")
    assert read_manifest(manifest) == [(tmp_path / "a/b/drive.mcap", Path("a/b/drive")),
                                       (tmp_path / "x" / "v.mp4", None)]
    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (tmp_path / "v.mp4").write_bytes(b"")
    assert is_recording(tmp_path / "bag") and not is_recording(tmp_path / "v.mp4")
    assert is_recording(tmp_path / "v.mp4", videos=True)
    (tmp_path / "bag" / "labels.csv").write_text("")
    (tmp_path / "bag" / "summary.json").write_text("{}")
    assert not is_recording(tmp_path / "bag")  # a replay output (a rosbag2 of labels)
    with pytest.raises(BagError, match="cannot read manifest"):
        read_manifest(tmp_path / "missing.txt")


def test_manifest_entries_that_leave_its_folder_go_under_their_name(tmp_path: Path) -> None:
    """``../x/drive.mcap`` would mirror to a path outside --out: such an entry (like an absolute
    one) writes under its name instead; a manifest that is not a regular file is one line."""
    import os

    import pytest

    from ficap_ros.errors import BagError
    from ficap_ros.tools.fleet.manifest import read_manifest

    (tmp_path / "lists").mkdir()
    manifest = tmp_path / "lists" / "m.txt"
    manifest.write_text("../in/d1.mcap\nsub/d2.mcap\n/abs/d3.mcap\n")
    entries = read_manifest(manifest)
    assert [rel for _, rel in entries] == [None, Path("sub/d2"), None]
    fifo = tmp_path / "m.fifo"
    os.mkfifo(fifo)
    with pytest.raises(BagError, match="not a regular file"):
        read_manifest(fifo)
