"""ficap_ros.files: the one rule every reader and writer follows. User files read only when regular
and small enough, text as UTF-8, YAML without aliases or deep nesting, or refused in one line;
single files written atomically; output folders built beside their target and swapped in whole;
never an output over an input, into a recording or a folder ficap did not write (every verb obeys
it); one writer per output (a lock); killed runs' temporaries removed, never a live run's."""

from __future__ import annotations

import errno
import os
import shutil
import signal
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from recordings import digest, one_error_line

from ficap_ros import files
from ficap_ros.cli.main import main
from ficap_ros.errors import CalibrationError, ConfigError, OutputError
from ficap_ros.files import (
    OutputFile,
    OutputFolder,
    OutputLock,
    check_not_in_recording,
    check_not_input,
    check_output_file,
    check_output_folder,
    check_replaceable,
    is_ficap_output,
    load_yaml,
    read_bytes,
    read_text,
    remove_stale_temporaries,
    write_atomic,
    write_output_file,
)


def test_replay_removes_temporaries_of_killed_runs_only(drive: Path, tmp_path: Path) -> None:
    """A run killed outright (SIGKILL) leaves its .ficap-NAME.* folder; the next replay into the
    same output removes it, but never a folder it cannot prove dead (no lock file: an older
    ficap's). While a live run writes the output, a second one is refused in one line and the
    live run's temporary stays."""
    out = tmp_path / "out"
    start = ("import os, signal, sys; from ficap_ros.files import OutputFolder; "
             f"f = OutputFolder({str(out)!r}); (f.tmp / 'labels.csv').write_text('half'); "
             "print(f.tmp, flush=True); ")
    killed = subprocess.run(
        [sys.executable, "-c", start + "os.kill(os.getpid(), signal.SIGKILL)"],
        capture_output=True, text=True, timeout=60)
    assert killed.returncode == -signal.SIGKILL
    dead = Path(killed.stdout.strip())
    legacy = tmp_path / ".ficap-out.abcd1234"
    legacy.mkdir()
    assert dead.is_dir()
    assert main(["replay", str(drive), "--out", str(out), "--quiet"]) == 0
    assert not dead.exists() and not Path(f"{dead}.lock").exists() and legacy.is_dir()
    assert (out / "labels.csv").read_text().startswith("frame,")
    live = subprocess.Popen([sys.executable, "-c", start + "sys.stdin.read()"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        alive = Path(live.stdout.readline().strip())
        second = subprocess.run([sys.executable, "-m", "ficap_ros.cli", "replay", str(drive),
                                 "--out", str(out), "--quiet"], capture_output=True, text=True,
                                timeout=120)
        assert second.returncode == 1, second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and "is being written by another ficap process (pid " in lines[0]
        assert alive.is_dir() and Path(f"{alive}.lock").exists()
        assert (out / "labels.csv").read_text().startswith("frame,")  # the first run's, intact
    finally:
        live.communicate("", timeout=60)
    assert live.returncode == 0  # it ends without committing: its own exit leaves its folder


def test_stats_evaluate_kit_and_fleet_never_write_into_a_recording_or_foreign_folder(
        drive: Path, replayed: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # They add files to --out rather than replace it, but under the same rule: a rosbag2
    # recording or a folder of the user's files is refused before anything is written.
    before = digest(drive)
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    tree = tmp_path / "tree"  # a fleet's --out that holds a recording deeper down
    shutil.copytree(drive, tree / "alice" / "d1")
    truth = f"{drive}:/ficap/truth/head_pose"
    for out in (drive, foreign, tree):
        for argv in (["stats", str(replayed), "--out", str(out)],
                     ["evaluate", "--truth", truth, "--estimate", str(replayed / "labels.csv"),
                      "--out", str(out)],
                     ["kit", "--out", str(out), "--no-stl"],
                     ["replay", str(drive), str(replayed.parent), "--out", str(out), "--quiet"]):
            assert main(argv) == 1, (argv, capsys.readouterr())
            line = one_error_line(capsys)
            assert ("did not write" in line or "the input" in line) and str(out) in line, line
    assert digest(drive) == before and digest(tree / "alice" / "d1") == before
    assert sorted(p.name for p in foreign.iterdir()) == ["notes.txt"]
    # A folder ficap wrote takes them all (each keeps the others' files), and stays one ficap
    # may replace; never the input's own folder.
    mine = tmp_path / "labels"
    shutil.copytree(replayed, mine)
    assert main(["stats", str(replayed), "--out", str(mine)]) == 0
    assert main(["evaluate", "--truth", truth, "--estimate", str(replayed / "labels.csv"),
                 "--out", str(mine)]) == 0
    assert main(["kit", "--out", str(mine), "--paper", "letter", "--no-stl"]) == 0
    assert {"stats.json", "report.md", "timeseries.png", "ficap_tags_letter.pdf", "labels.csv"} <= {
        p.name for p in mine.iterdir()}
    for argv in (["stats", str(mine), "--out", str(mine)],
                 ["stats", str(mine), "--out", str(mine / "sub")]):
        assert main(argv) == 1
        assert "is, holds or lies inside the input" in one_error_line(capsys)
    assert main(["replay", str(drive), "--out", str(mine), "--quiet"]) == 0
    assert sorted(p.name for p in mine.iterdir()) == sorted(p.name for p in replayed.iterdir())


def test_a_symlink_in_an_output_folder_is_the_users(tmp_path: Path) -> None:
    # ficap never writes a symlink, so one inside --out (to a folder or a file) points at the
    # user's data: a run that replaced or wrote through it would land outside --out.
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "labels.csv").write_text("not ficap's")
    single, fleet = tmp_path / "single", tmp_path / "fleet"
    single.mkdir()
    (single / "labels.csv").write_text("t\n")
    (fleet / "d1").mkdir(parents=True)
    (fleet / "d1" / "labels.csv").write_text("t\n")
    check_replaceable(single)  # ficap's own outputs: replaceable
    check_replaceable(fleet, subfolders=True)
    for out, subfolders in ((single, False), (fleet, True)):
        (out / "link").symlink_to(elsewhere, target_is_directory=True)
        with pytest.raises(OutputError, match="link/"):
            check_replaceable(out, subfolders=subfolders)
        (out / "link").unlink()
    (fleet / "d1" / "summary.json").symlink_to(elsewhere / "labels.csv")  # a file, deeper down
    with pytest.raises(OutputError, match="summary.json"):
        check_replaceable(fleet, subfolders=True)
    assert (elsewhere / "labels.csv").read_text() == "not ficap's"


# -- reading -------------------------------------------------------------------------------------
@given(text=st.text(st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",))))
def test_text_reads_back_as_written(tmp_path_factory: pytest.TempPathFactory, text: str) -> None:
    path = tmp_path_factory.mktemp("read") / "notes.yaml"
    path.write_bytes(text.encode("utf-8"))
    assert read_text(path, "notes", ConfigError) == text


def test_what_is_not_text_is_the_callers_error_in_one_line(tmp_path: Path) -> None:
    cases = {"nul.yaml": (b"a: 1\x00", "is a binary file, not text"),
             "utf16.yaml": ("a: 1".encode("utf-16"), "is a binary file, not text"),
             "latin1.yaml": ("caf\xe9: 1".encode("latin-1"), r"is not UTF-8 text \(byte 3\)")}
    for name, (data, says) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(CalibrationError, match=says) as info:
            read_text(tmp_path / name, "calibration", CalibrationError)
        assert str(info.value).startswith(f"calibration {tmp_path / name} ")
    with pytest.raises(CalibrationError, match="is a folder, not a file"):
        read_text(tmp_path, "calibration", CalibrationError)
    with pytest.raises(CalibrationError, match="cannot read calibration .*No such file"):
        read_text(tmp_path / "missing.yaml", "calibration", CalibrationError)


# -- single files --------------------------------------------------------------------------------
@given(data=st.one_of(st.binary(max_size=5000), st.text(max_size=500)))
def test_an_atomic_write_reads_back_and_leaves_nothing_beside_it(
        tmp_path_factory: pytest.TempPathFactory, data: bytes | str) -> None:
    folder = tmp_path_factory.mktemp("atomic")
    path = folder / "out.json"
    path.write_text("old")
    write_atomic(path, data)
    assert path.read_bytes() == (data.encode() if isinstance(data, str) else data)
    assert [p.name for p in folder.iterdir()] == ["out.json"]


def test_an_atomic_write_takes_the_umasks_permissions(tmp_path: Path) -> None:
    old = os.umask(0o027)
    try:
        write_atomic(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o640


@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device"),
                                     KeyboardInterrupt()])
def test_a_failed_write_leaves_the_old_file_and_no_temporary(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failure: BaseException) -> None:
    path = tmp_path / "labels.csv"
    path.write_text("the old labels")

    def fail(fd: int) -> None:
        raise failure

    monkeypatch.setattr(files.os, "fsync", fail)
    with pytest.raises(type(failure)):
        write_atomic(path, "half of the new labels")
    assert path.read_text() == "the old labels"
    assert [p.name for p in tmp_path.iterdir()] == ["labels.csv"]
    new = tmp_path / "new.csv"  # nothing under the final name when there was no old file
    if isinstance(failure, OSError):
        with pytest.raises(OutputError, match=f"cannot write report {new}: No space left"):
            write_output_file(new, "x", what="report")
        assert not new.exists() and [p.name for p in tmp_path.iterdir()] == ["labels.csv"]


def test_an_output_file_is_never_an_input_a_folder_or_in_a_missing_folder(tmp_path: Path) -> None:
    data = tmp_path / "drive.mcap"
    data.write_bytes(b"recording")
    with pytest.raises(OutputError, match="is, holds or lies inside the input"):
        write_output_file(data, "labels", inputs=[data])
    link = tmp_path / "link.mcap"
    link.symlink_to(data)
    with pytest.raises(OutputError, match="is, holds or lies inside the input"):
        write_output_file(link, "labels", inputs=[data])  # the same file under another name
    assert data.read_bytes() == b"recording"
    with pytest.raises(OutputError, match="is a folder; give a file name"):
        write_output_file(tmp_path, "x")
    with pytest.raises(OutputError, match="folder .*nodir does not exist"):
        write_output_file(tmp_path / "nodir" / "x.yaml", "x")
    write_output_file(tmp_path / "ok.yaml", "x", inputs=[data])
    assert (tmp_path / "ok.yaml").read_text() == "x"


def test_outputs_and_inputs_never_overlap(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    bag.mkdir()
    for out in (bag, tmp_path, bag / "labels"):  # the input, a folder holding it, one inside it
        with pytest.raises(OutputError, match=f"input {bag}"):
            check_not_input(out, ["/elsewhere/other.mcap", bag])
    check_not_input(tmp_path / "labels", [bag])  # beside it
    check_not_input(tmp_path / "bag_labels", [bag])  # a longer name is no child


# -- output folders -------------------------------------------------------------------------------
def test_which_names_ficap_writes() -> None:
    for name in ("labels.csv", "labels.mcap", "metadata.yaml", "fleet_summary.png",
                 ".ficap-out.abc.lock", "ficap_tags_a4.pdf", "ficap_tags_letter_p2.svg",
                 "ficap_assembly.png", "ficap_shell.stl"):
        assert is_ficap_output(name), name
    for name in ("notes.txt", "labels.csv.bak", "ficap_tags_a3.pdf", "ficap_tags_a4_p1.pdf",
                 "drive_0.mcap", "ficap_shell.obj"):
        assert not is_ficap_output(name), name


def test_a_folder_is_replaceable_only_when_ficap_wrote_it(tmp_path: Path) -> None:
    out = tmp_path / "out"
    check_replaceable(out)  # not there yet
    out.mkdir()
    check_replaceable(out)  # empty
    (out / "labels.csv").write_text("x")
    (out / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  relative_file_paths: [labels.mcap]\n")
    check_replaceable(out)  # replay's own output
    (out / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  relative_file_paths: [drive_0.mcap]\n")
    with pytest.raises(OutputError, match="is a rosbag2 recording ficap did not write"):
        check_replaceable(out)
    (out / "metadata.yaml").write_text("just: notes\n")
    with pytest.raises(OutputError, match="holds a metadata.yaml ficap did not write"):
        check_replaceable(out)
    (out / "metadata.yaml").unlink()
    for name in ("a.txt", "b.txt", "c.txt", "d.txt"):
        (out / name).write_text("mine")
    with pytest.raises(OutputError, match=r"\(a.txt, b.txt, c.txt \.\.\.\); choose a new or empty"):
        check_replaceable(out)
    with pytest.raises(OutputError, match="exists and is not a folder"):
        check_replaceable(out / "a.txt")
    fleet = tmp_path / "fleet"
    (fleet / "alice" / "d1").mkdir(parents=True)
    (fleet / "alice" / "d1" / "summary.json").write_text("{}")
    with pytest.raises(OutputError, match="alice/"):
        check_replaceable(fleet)  # a folder in a single output is not ficap's
    check_replaceable(fleet, subfolders=True)
    (fleet / "alice" / "d1" / "video.mp4").write_bytes(b"")
    with pytest.raises(OutputError, match="video.mp4"):
        check_replaceable(fleet, subfolders=True)  # at any depth


def test_check_output_folders(tmp_path: Path) -> None:
    made = tmp_path / "a" / "b"
    assert check_output_folder(made) == made
    check_output_folder(tmp_path / "x" / "y" / "z")  # created later, from the first that exists
    assert not (tmp_path / "x").exists()  # the check creates nothing
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError, match=f"{blocker} is not a folder"):
        check_output_folder(blocker / "out")


def test_an_output_folder_is_swapped_in_whole_or_not_at_all(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with OutputFolder(out) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".ficap-out.") and not out.exists()
        (tmp / "labels.csv").write_text("first")
        (tmp / "summary.json").write_text("{}")
    assert sorted(p.name for p in out.iterdir()) == ["labels.csv", "summary.json"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporary, no lock left
    with pytest.raises(RuntimeError):
        with OutputFolder(out) as tmp:
            (tmp / "labels.csv").write_text("second, interrupted")
            raise RuntimeError("the run failed")
    assert (out / "labels.csv").read_text() == "first" and (out / "summary.json").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    with OutputFolder(out) as tmp:
        (tmp / "labels.csv").write_text("third")
    assert [p.name for p in out.iterdir()] == ["labels.csv"]  # replaced as a unit: no summary.json
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    with pytest.raises(OutputError, match="lies inside the input"):
        OutputFolder(out / "sub", inputs=[out])


def test_stale_temporaries_go_live_ones_and_unlocked_ones_stay(tmp_path: Path) -> None:
    import fcntl

    out = tmp_path / "out"
    dead = tmp_path / ".ficap-out.dead1234"
    live = tmp_path / ".ficap-out.live5678"
    legacy = tmp_path / ".ficap-out.abcd0000"  # no lock file: never taken for stale
    aside = tmp_path / f".ficap-out.old-{os.getpid()}"
    for folder in (dead, live, legacy, aside):
        folder.mkdir()
        (folder / "labels.csv").write_text("half")
    Path(f"{dead}.lock").write_text("")
    Path(f"{live}.lock").write_text("")
    fd = os.open(f"{live}.lock", os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # a live run holds its lock
        assert remove_stale_temporaries(out) == [dead]
        assert not dead.exists() and not Path(f"{dead}.lock").exists()
        assert live.is_dir() and legacy.is_dir() and aside.is_dir()
    finally:
        os.close(fd)
    assert remove_stale_temporaries(out) == [live]  # let go: the run is gone
    assert remove_stale_temporaries(tmp_path / "other") == []


# -- the guarded reader ---------------------------------------------------------------------------
def test_only_regular_files_no_larger_than_their_limit_are_read(tmp_path: Path) -> None:
    """A FIFO is refused without blocking, a device without reading it, a file over its limit
    before a byte of it is read."""
    fifo = tmp_path / "cal.fifo"
    os.mkfifo(fifo)
    with pytest.raises(CalibrationError, match="is not a regular file"):
        read_text(fifo, "calibration", CalibrationError)  # would block for ever if opened plainly
    with pytest.raises(CalibrationError, match="/dev/zero is not a regular file"):
        read_bytes("/dev/zero", "calibration", CalibrationError)
    big = tmp_path / "big.yaml"
    with open(big, "wb") as handle:
        handle.truncate(files.MAX_CONFIG_BYTES + 1)  # sparse: nothing written
    with pytest.raises(CalibrationError, match=f"is {files.MAX_CONFIG_BYTES + 1} bytes, more than"):
        read_text(big, "calibration", CalibrationError)
    assert read_bytes(big, "x", CalibrationError, limit=files.MAX_CONFIG_BYTES + 1)[:4] == bytes(4)


@pytest.mark.parametrize("text, says", [
    ("a: &x [1, 2]\nb: *x\n", "line 2: aliases"),
    # the classic billion laughs, stopped at its first alias before anything expands
    ("a: &a [x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
     "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\n", "aliases"),
    ("x: " + "[" * 100_000 + "]" * 100_000 + "\n", "nested deeper than 32 levels"),
    ("x: " + "9" * 5000 + "\n", "an integer of 5000 digits"),
    ("x: [1, 2\n", "not valid YAML: line 2"),
])
def test_yaml_without_aliases_deep_nesting_or_huge_integers(tmp_path: Path, text: str,
                                                           says: str) -> None:
    import time

    path = tmp_path / "config.yaml"
    path.write_text(text)
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=says) as info:
        load_yaml(path, "config", ConfigError)
    assert time.perf_counter() - t0 < 5.0
    assert "\n" not in str(info.value) and str(info.value).startswith(f"config {path} ")


def test_ordinary_yaml_reads_back(tmp_path: Path) -> None:
    path = tmp_path / "config.yaml"
    path.write_text("a: &anchor [1, 2.5, -3]\nb: {c: [[1, 2], [3, 4]], d: true}\nbig: "
                    "9223372036854775807\n")
    assert load_yaml(path, "config", ConfigError) == {
        "a": [1, 2.5, -3], "b": {"c": [[1, 2], [3, 4]], "d": True}, "big": 2**63 - 1}


# -- the output rule for single files, locks and links -------------------------------------------
def test_no_output_inside_a_recording_or_over_one(tmp_path: Path) -> None:
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  relative_file_paths: [bag_0.mcap]\n")
    (bag / "bag_0.mcap").write_bytes(b"\x89MCAP0\r\n")
    for target in (bag / "metadata.yaml", bag / "model.yaml", bag / "deep" / "er" / "x.yaml"):
        with pytest.raises(OutputError, match=f"lies inside the recording {bag}"):
            check_not_in_recording(target)
    disguised = tmp_path / "labels.yaml"  # a recording by content, whatever its name
    disguised.write_bytes(b"SQLite format 3\x00" + bytes(100))
    with pytest.raises(OutputError, match="is a recording; ficap never overwrites one"):
        check_output_file(disguised)
    (tmp_path / "drive.mp4").write_bytes(b"")  # a recording by its name
    with pytest.raises(OutputError, match="is a recording"):
        check_output_file(tmp_path / "drive.mp4")
    mine = tmp_path / "labels"  # ficap's own labels bag is no recording: stats may go inside
    mine.mkdir()
    (mine / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  relative_file_paths: [labels.mcap]\n")
    check_not_in_recording(mine / "stats" / "x.png")


def test_output_locks_refuse_other_processes_and_go_when_released(tmp_path: Path) -> None:
    target = tmp_path / "model.yaml"
    code = ("import sys; from ficap_ros.errors import OutputError; from ficap_ros.files import "
            f"OutputFile\ntry:\n    OutputFile({str(target)!r}, what='cap model')\nexcept "
            "OutputError as err:\n    print(err); sys.exit(3)\n")
    with OutputFile(target, what="cap model") as out:
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=60)
        assert run.returncode == 3, run.stderr
        assert f"cap model {target} is being written by another ficap process (pid " \
            f"{os.getpid()})" in run.stdout
        with OutputLock(target):  # the same process nests
            pass
        out.write("tags: []\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model.yaml"]  # no lock file left
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stdout


def test_symlinked_outputs(tmp_path: Path) -> None:
    """--out as a link to a folder writes the folder (the link stays, no .old link left); a link
    that leads nowhere (a loop, a missing target) is refused before any processing."""
    real = tmp_path / "real"
    real.mkdir()
    link = tmp_path / "link"
    link.symlink_to(real, target_is_directory=True)
    with OutputFolder(link) as tmp:
        (tmp / "labels.csv").write_text("x")
    assert link.is_symlink() and (real / "labels.csv").read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "real"]
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    for check in (check_output_folder, check_output_file):
        with pytest.raises(OutputError, match="symbolic link that leads nowhere"):
            check(loop)
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    with pytest.raises(OutputError, match="leads nowhere"):
        OutputFolder(tmp_path / "dangling")


def test_immutable_outputs_are_refused_before_any_processing(tmp_path: Path) -> None:
    """chattr +i: renaming the folder (or replacing the file) would fail at the very end."""
    if subprocess.run(["chattr", "+i", str(tmp_path)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not available here (needs CAP_LINUX_IMMUTABLE)")
    subprocess.run(["chattr", "-i", str(tmp_path)], check=True)
    out = tmp_path / "out"
    out.mkdir()
    model = tmp_path / "model.yaml"
    model.write_text("tags: []\n")
    subprocess.run(["chattr", "+i", str(out), str(model)], check=True)
    try:
        with pytest.raises(OutputError, match="immutable"):
            check_output_folder(out)
        with pytest.raises(OutputError, match="immutable"):
            check_output_file(model)
    finally:
        subprocess.run(["chattr", "-i", str(out), str(model)], check=True)


def test_a_merging_output_folder_keeps_the_files_it_does_not_write(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with OutputFolder(out) as tmp:
        (tmp / "stats.json").write_text("old stats")
        (tmp / "report.md").write_text("old report")
    inode = (out / "report.md").stat().st_ino
    with OutputFolder(out, merge=True) as tmp:
        (tmp / "stats.json").write_text("new stats")
    assert (out / "stats.json").read_text() == "new stats"
    assert (out / "report.md").read_text() == "old report"
    assert (out / "report.md").stat().st_ino == inode  # linked, not copied
    with pytest.raises(RuntimeError):
        with OutputFolder(out, merge=True) as tmp:
            (tmp / "stats.json").write_text("half")
            raise RuntimeError("the verb failed")
    assert (out / "stats.json").read_text() == "new stats"
