"""Bad inputs against every reader and verb that takes them: the corpus (test/data/bad_inputs,
written by test/helpers/make_bad_inputs.py), files that are not text, and random and damaged files
(hypothesis). Each gives a one-line error, a recovered result or a labelled skip, never a
traceback.

It mirrors no module of ficap_ros (test_package.py's ``UNMIRRORED`` says why): bad inputs cross
every reader and verb, and one corpus serves them all.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from mutations import mutated
from probe_cases import (
    BAD_NUMBERS,
    QUICK_REFUSALS,
    Probe,
    Run,
    camera_info_with,
    check_run,
    extend_sparse,
    flip_bytes,
    huge_jpeg_header,
    jpeg_bag,
    run_cli,
    sha256s,
    walk_cases,
)
from recordings import CORRUPT_BAG_FRAMES, one_error_line, small_bag

from ficap_ros.cli.args import EXIT_FRAMES_LOST
from ficap_ros.cli.main import main
from ficap_ros.errors import (
    BagError,
    CalibrationError,
    FicapError,
    IntrinsicsError,
    ModelError,
)
from ficap_ros.geometry.camera import CameraModel, load_camera_yaml
from ficap_ros.geometry.cap_model import load_model, nominal_model
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.calibration_file import load_calibration
from ficap_ros.io.image_codec import decode_compressed
from ficap_ros.io.labels import LABEL_COLUMNS, read_labels
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.sources import (
    CAMERA_INFO_TYPE,
    IMAGE_TYPE,
    open_bag_reader,
    open_frames,
)

CORPUS = Path(__file__).resolve().parent / "data" / "bad_inputs"
BAGS = sorted([p for p in CORPUS.glob("*.mcap")] + [p for p in CORPUS.iterdir() if p.is_dir()])
IMAGES = sorted([*CORPUS.glob("*.jpg"), *CORPUS.glob("*.png")])
INTRINSICS = sorted(CORPUS.glob("intrinsics_*.yaml"))
CALIBRATIONS = sorted(CORPUS.glob("calibration_*.yaml"))
MODELS = sorted(CORPUS.glob("model_*.yaml"))
LABELS = sorted(CORPUS.glob("labels_*.csv"))
#: A valid bag of the corpus (tags 5 5 / 300 586 / 3 300) to pair with bad side files.
VALID_BAG = CORPUS / "bag_duplicated_and_foreign_ids.mcap"

#: Exit codes of ``ficap replay`` where the outcome is known exactly; others must be 0, 1 or 3.
REPLAY_EXPECTED = {
    "mcap_truncated.mcap": EXIT_FRAMES_LOST,  # recovered: frames before the cut, loss reported
    "sqlite_torn": EXIT_FRAMES_LOST,
    "not_a_bag.mcap": 1,
    "mcap_magic_only.mcap": 1,
    "metadata_binary": 1,
    "sqlite_garbage": 1,
    "bag_wrong_encoding.mcap": 1,  # every frame skipped
    "bag_unknown_encoding.mcap": 1,
    "bag_camera_info_zero.mcap": 1,  # no valid CameraInfo and no --intrinsics
    "bag_camera_info_nan.mcap": 1,
    "bag_camera_info_p_only.mcap": 0,  # P is enough (the node's rule)
    "bag_broken_jpeg.mcap": 0,  # two of four skipped, labelled
    "bag_duplicated_and_foreign_ids.mcap": 0,
}


def test_corpus_is_present_and_small() -> None:
    files = [p for p in CORPUS.rglob("*") if p.is_file()]
    assert len(files) >= 45
    assert sum(p.stat().st_size for p in files) < 1_000_000


def _check_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> int:
    code = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    assert code in (0, 1, EXIT_FRAMES_LOST), (argv, code, err)
    if code == 1:
        errors = [ln for ln in err.strip().splitlines() if ln.startswith("ficap: error:")]
        assert len(errors) == 1, err
    return code


@pytest.mark.parametrize("bag", BAGS, ids=lambda p: p.name)
def test_bags_through_every_verb(bag: Path, tmp_path: Path,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    code = _check_cli(["replay", str(bag), "--out", str(out), "--quiet"], capsys)
    if bag.name in REPLAY_EXPECTED:
        assert code == REPLAY_EXPECTED[bag.name]
    if code in (0, EXIT_FRAMES_LOST):
        summary = json.loads((out / "summary.json").read_text())
        assert sum(summary["skipped_reasons"].values()) == summary["frames_skipped"]
        assert (summary["lost"] is not None) == (code == EXIT_FRAMES_LOST)
    _check_cli(["stats", str(bag), "--quiet"], capsys)
    _check_cli(["model", "build", str(bag), "--out", str(tmp_path / "m.yaml"), "--quiet"], capsys)
    _check_cli(["evaluate", "--truth", f"{bag}:/head_pose", "--estimate", f"{bag}:/head_pose",
                "--out", str(tmp_path / "ev"), "--no-plots"], capsys)


@pytest.mark.parametrize("bag", BAGS, ids=lambda p: p.name)
def test_bag_readers_raise_only_ficap_errors(bag: Path) -> None:
    try:
        source = open_frames(bag)
        frames = list(source.frames())
    except FicapError:
        return
    for frame in frames:
        assert (frame.image is None) == (frame.error is not None)
    reader = open_bag_reader(bag)
    reader.close()


def test_duplicated_and_foreign_ids_are_kept_out_of_the_pose(tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main(["replay", str(VALID_BAG), "--out", str(out), "--quiet"]) == 0
    rows = (out / "labels.csv").read_text().splitlines()[1:]
    ids = [r.split(",")[LABEL_COLUMNS.index("used_ids")] for r in rows]
    assert ids[1] == ""  # 300 and 586 are not cap tags
    assert ids[2] == "3"


@pytest.mark.parametrize("image", IMAGES, ids=lambda p: p.name)
def test_images_through_detect_and_the_decoder(image: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    code = _check_cli(["detect", str(image)], capsys)
    # A JPEG cut short or corrupt is refused (libjpeg would make up the missing rows).
    expected = {"tags_duplicated_ids.png": 0, "tags_foreign_ids.png": 0}
    assert code == expected.get(image.name, 1)
    try:
        decode_compressed(image.read_bytes())
    except FicapError:
        pass


def test_detect_lists_duplicated_and_foreign_ids(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["detect", "--json", str(CORPUS / "tags_duplicated_ids.png"),
                 str(CORPUS / "tags_foreign_ids.png")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [d["id"] for d in out[0]["detections"]] == [5, 5]
    assert sorted(d["id"] for d in out[1]["detections"]) == [300, 586]


@pytest.mark.parametrize("path", INTRINSICS, ids=lambda p: p.name)
def test_bad_intrinsics(path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(FicapError):
        load_camera_yaml(path)
    assert _check_cli(["replay", str(VALID_BAG), "--out", str(tmp_path / "o"), "--intrinsics",
                       str(path), "--quiet"], capsys) == 1


@pytest.mark.parametrize("path", CALIBRATIONS, ids=lambda p: p.name)
def test_bad_calibrations(path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(FicapError):
        load_calibration(path)
    assert _check_cli(["replay", str(VALID_BAG), "--out", str(tmp_path / "o"), "--calibration",
                       str(path), "--quiet"], capsys) == 1


@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.name)
def test_bad_models(path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(FicapError):
        load_model(path)
    assert _check_cli(["model", "--model", str(path)], capsys) == 1
    assert _check_cli(["replay", str(VALID_BAG), "--out", str(tmp_path / "o"), "--model",
                       str(path), "--quiet"], capsys) == 1


@pytest.mark.parametrize("path", LABELS, ids=lambda p: p.name)
def test_bad_labels(path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    try:
        labels = read_labels(path)
    except FicapError:
        labels = None
    if path.name == "labels_torn_row.csv":
        assert labels is not None and len(labels.stamp_ns) == 1  # the torn row is no frame
    stats = _check_cli(["stats", str(path)], capsys)
    assert stats == (0 if labels is not None else 1)
    _check_cli(["calibrate", str(path), "--frontal", "0:1", "--out", str(tmp_path / "c.yaml")],
               capsys)
    _check_cli(["evaluate", "--truth", str(path), "--estimate", str(path), "--out",
                str(tmp_path / "ev"), "--no-plots"], capsys)


def test_node_starts_or_refuses_in_one_line_on_every_bad_file(probe) -> None:  # noqa: ANN001
    """The node's three file parameters with every bad YAML of the corpus and the probe's
    hostile files (5000 digits, 100k-deep nesting, an alias bomb, a FIFO, /dev/zero): it starts
    uncalibrated or without static intrinsics, or (a model: it cannot run without one) refuses
    in one line (real rclpy)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from ficap_ros.ros.node import FicapNode

    cfg = probe.files
    hostile = [cfg / "cal_bigint.yaml", cfg / "cal_deep.yaml", cfg / "cal_laughs.yaml",
               probe.fifo, Path("/dev/zero")]
    context = Context()
    rclpy.init(context=context)
    try:
        for param, files, fatal in (
                ("camera_info_file", [*INTRINSICS, *hostile, cfg / "intr_d6.yaml"], False),
                ("calibration.file", [*CALIBRATIONS, *hostile, cfg / "cal_q1e308.yaml",
                                      cfg / "cal_qbool.yaml"], False),
                ("model_file", [*MODELS, *hostile, cfg / "model_id587.yaml"], True)):
            for path in files:
                try:
                    node = FicapNode(context=context,
                                     parameter_overrides=[Parameter(param, value=str(path))])
                except FicapError as err:
                    assert fatal, (param, path, err)
                    assert "\n" not in str(err)
                    continue
                assert not fatal, (param, path)
                assert not node.calibration.calibrated
                node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_missing_paths_are_one_line_on_the_real_stderr(tmp_path: Path) -> None:
    """In a real process (file descriptor 2, where OpenCV prints its own WARN lines, not
    capsys): a path that does not exist is exactly one ``ficap: error:`` line and exit 1."""
    import subprocess
    import sys

    missing = str(tmp_path / "nope.png")
    for argv in (["detect", missing], ["detect", str(tmp_path)],
                 ["stats", str(tmp_path / "nope.mcap")],
                 ["replay", str(tmp_path / "nope.mp4"), "--out", str(tmp_path / "o")]):
        run = subprocess.run([sys.executable, "-m", "ficap_ros.cli", *argv], capture_output=True,
                             text=True, timeout=120)
        lines = run.stderr.strip().splitlines()
        assert run.returncode == 1 and len(lines) == 1, (argv, run.stderr)
        assert lines[0].startswith("ficap: error:") and argv[1] in lines[0], lines


def test_a_bad_number_in_labels_is_named_by_row_and_column(tmp_path: Path) -> None:
    """Not Python's 'invalid literal for int() with base 10': the row and the column."""
    with pytest.raises(FicapError, match=r"row 2, stamp_ns: not a number: 'soon'"):
        read_labels(CORPUS / "labels_bad_numbers.csv")
    good = (CORPUS / "labels_bad_numbers.csv").read_text().splitlines()
    header = good[0].split(",")
    row = ["1"] * len(header)
    row[header.index("reliability")] = "high"
    path = tmp_path / "labels.csv"
    path.write_text("\n".join([good[0], ",".join(row)]) + "\n")
    with pytest.raises(FicapError, match=r"row 2, reliability: not a number: 'high'"):
        read_labels(path)


def test_a_100_byte_mcap_is_named_truncated_in_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The first 100 bytes of a real MCAP: not rosbags' 'File end magic is invalid.' but one line
    naming the file, saying it is cut short, and exit 1 (bad input) from replay and stats."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((CORPUS / "mcap_truncated.mcap").read_bytes()[:100])
    for argv in (["replay", str(cut), "--out", str(tmp_path / "o"), "--quiet"],
                 ["stats", str(cut), "--quiet"]):
        assert main(argv) == 1, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("ficap: error:"), err
        assert str(cut) in err[0] and "truncated" in err[0], err
        assert "not a complete MCAP file" in err[0] and "magic" not in err[0], err


# -- files that are not text -----------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["bin", "utf16"])
def test_loaders_refuse_binary_and_non_utf8_files(binary_files: dict[str, Path], kind: str) -> None:
    path = binary_files[kind]
    for loader, error in ((load_calibration, CalibrationError), (load_camera_yaml, IntrinsicsError),
                          (load_model, ModelError), (read_labels, BagError)):
        with pytest.raises(error) as info:
            loader(path)
        assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_cli_verbs_refuse_binary_files(drive: Path, replayed: Path, binary_files: dict[str, Path],
                                       tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = str(binary_files["bin"])
    out = str(tmp_path / "o")
    for option in ("--calibration", "--intrinsics", "--model"):
        assert main(["replay", str(drive), "--out", out, option, bad, "--quiet"]) == 1
        assert bad in one_error_line(capsys)
    labels_mcap = str(replayed / "labels.mcap")
    assert main(["evaluate", "--truth", labels_mcap, "--estimate", labels_mcap,
                 "--out", out]) == 1
    one_error_line(capsys)
    assert main(["calibrate", labels_mcap, "--frontal", "0:2", "--out",
                 str(tmp_path / "c.yaml")]) == 1
    one_error_line(capsys)
    assert not (tmp_path / "o").exists()


# -- random and damaged files (hypothesis): only FicapError, or a result --------------------------
CAM = CameraModel(64, 48, np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]]),
                  np.array([0.1, -0.05, 0.0, 0.0, 0.0]), "plumb_bob")
IMAGE = np.random.default_rng(1).integers(0, 256, (48, 64), dtype=np.uint8)
CAMERA_YAML = yaml.safe_dump(CAM.to_camera_yaml())
CALIBRATION_YAML = ("format: ficap_calibration/1\nquaternion_order: wxyz\ncalibrated: true\n"
                    "R_cap_head_q_wxyz: [0.99, 0.01, -0.1, 0.02]\n"
                    "R_cam_frontal_q_wxyz: [0.5, -0.5, 0.5, -0.5]\n")
LABELS_CSV = (
    "frame,stamp_ns,frame_id,tags_detected,tags_used,rms_px,reliability,cap_qw,cap_qx,cap_qy,"
    "cap_qz,cap_x_m,cap_y_m,cap_z_m,head_qw,head_qx,head_qy,head_qz,head_yaw_deg,"
    "head_pitch_deg,head_roll_deg,calibrated,detected_ids,reason\n"
    "0,1000,cam,2,2,0.1,0.9,1,0,0,0,0,0,0.6,1,0,0,0,0,0,0,0,3 7,\n"
    "1,2000,cam,0,0,,,,,,,,,,,,,,,,,0,,no tag\n")


def _write(tmp: Path, name: str, data: bytes) -> Path:
    path = tmp / name
    path.write_bytes(data)
    return path


@pytest.fixture(scope="module")
def scratch() -> Path:
    path = Path(tempfile.mkdtemp(prefix="ficap-fuzz-"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


@given(data=st.one_of(st.binary(max_size=2000), mutated(CAMERA_YAML.encode())))
def test_camera_yaml_raises_only_ficap_errors(scratch: Path, data: bytes) -> None:
    try:
        load_camera_yaml(_write(scratch, "camera.yaml", data))
    except FicapError:
        pass


@given(data=st.one_of(st.binary(max_size=2000), mutated(CALIBRATION_YAML.encode())))
def test_calibration_yaml_raises_only_ficap_errors(scratch: Path, data: bytes) -> None:
    try:
        cal = load_calibration(_write(scratch, "calibration.yaml", data))
    except FicapError:
        return
    assert isinstance(cal.calibrated, bool)


@given(data=mutated(nominal_model().to_yaml().encode()))
def test_model_yaml_raises_only_ficap_errors(scratch: Path, data: bytes) -> None:
    try:
        load_model(_write(scratch, "model.yaml", data))
    except FicapError:
        pass


@given(data=st.one_of(st.binary(max_size=2000), mutated(LABELS_CSV.encode())))
def test_labels_csv_raises_only_ficap_errors(scratch: Path, data: bytes) -> None:
    try:
        labels = read_labels(_write(scratch, "labels.csv", data))
    except FicapError:
        return
    assert len(labels.stamp_ns) == len(labels.reliability)


@pytest.fixture(scope="module")
def fuzz_bag(scratch: Path) -> Path:
    path = scratch / "bag"
    with BagWriter(path) as w:
        w.add_topic("/cam/image_raw", IMAGE_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        for i in range(4):
            head = messages.header(ROSBAGS, i + 1, "cam")
            w.write("/cam/camera_info", i + 1, messages.camera_info(ROSBAGS, head, CAM))
            w.write("/cam/image_raw", i + 1, messages.image(ROSBAGS, head, IMAGE, "mono8"))
    return path


def _read_all(path: Path) -> None:
    try:
        source = open_frames(path)
        for frame in source.frames():
            assert (frame.image is None) == (frame.error is not None)
        if source.loss is not None:
            assert "\n" not in source.loss.describe(source.start_ns)
    except FicapError:
        pass


@settings(max_examples=40)
@given(data=st.data())
def test_bag_metadata_raises_only_ficap_errors(fuzz_bag: Path, scratch: Path, data: st.DataObject
                                               ) -> None:
    meta = (fuzz_bag / "metadata.yaml").read_bytes()
    target = scratch / "meta_bag"
    shutil.rmtree(target, ignore_errors=True)
    shutil.copytree(fuzz_bag, target)
    (target / "metadata.yaml").write_bytes(data.draw(mutated(meta)))
    _read_all(target)


@settings(max_examples=40)
@given(data=st.data())
def test_mcap_bytes_raise_only_ficap_errors(fuzz_bag: Path, scratch: Path, data: st.DataObject
                                            ) -> None:
    mcap = next(fuzz_bag.glob("*.mcap")).read_bytes()
    _read_all(_write(scratch, "fuzzed.mcap", data.draw(mutated(mcap))))


# -- the fault probe's cases ------------------------------------------------------------------------
# Every case: the right exit (1 an error, 2 a bad argument, 3 frames salvaged from damage, 0 done),
# one line naming the problem, no traceback, the inputs' bytes unchanged, within 30 s and 500 MB
# (``probe_cases.check_run``). The inputs are built here, small or sparse.


@pytest.fixture(scope="module")
def probe(tmp_path_factory: pytest.TempPathFactory, rendered_frames) -> Probe:  # noqa: ANN001
    return Probe(tmp_path_factory.mktemp("probe"), rendered_frames)


def _case(probe: Probe, tmp_path: Path, argv: list, code: int, says: str,
          env: dict[str, str] | None = None, capsys: pytest.CaptureFixture[str] | None = None,
          ) -> str:
    """One case, checked (``check_run``) with the inputs' bytes before and after: in a child
    process (peak memory measured), or in this one with ``capsys`` (a case refused before any
    frame is read, where a child would only add its start-up)."""
    import time

    before = sha256s(probe.inputs())
    if capsys is None:
        run = run_cli(argv, tmp_path, env=env)
    else:
        saved = {k: os.environ.get(k) for k in env or {}}
        os.environ.update(env or {})
        try:
            t0 = time.monotonic()
            code_got = main([str(a) for a in argv])
            captured = capsys.readouterr()
            run = Run(code_got, captured.out, captured.err, time.monotonic() - t0, 0.0)
        finally:
            for k, v in saved.items():
                os.environ.pop(k) if v is None else os.environ.__setitem__(k, v)
    line = check_run(run, code, says)
    assert sha256s(probe.inputs()) == before
    return line


@pytest.mark.parametrize("argv, code, says", [c[1:] for c in QUICK_REFUSALS],
                         ids=[c[0] for c in QUICK_REFUSALS])
def test_probe_cases_refused_before_any_processing(probe: Probe, tmp_path: Path, argv: list[str],
                                                   code: int, says: str,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    names = {"bag": probe.bag, "single": probe.single.parent, "model": probe.model,
             "cfg": probe.files, "fifo": probe.fifo, "out": tmp_path / "out"}
    _case(probe, tmp_path, [a.format(**names) for a in argv], code, says, capsys=capsys)
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.yaml").exists()


@pytest.mark.parametrize("argv", BAD_NUMBERS, ids=lambda a: "-".join(a[:1] + a[-2:]))
def test_probe_numbers_out_of_range_are_argparse_errors(probe: Probe, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str],
                                                        argv: list[str]) -> None:
    import time

    before = sha256s(probe.inputs())
    t0 = time.monotonic()
    with pytest.raises(SystemExit) as stop:
        main([a.format(bag=probe.bag, out=tmp_path / "out") for a in argv])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and time.monotonic() - t0 < 5.0
    assert "Traceback" not in err and len([ln for ln in err.splitlines() if "error:" in ln]) == 1
    assert "error: argument" in err.splitlines()[-1], err
    assert sha256s(probe.inputs()) == before and not (tmp_path / "out").exists()


def test_probe_bad_camera_info_in_a_bag_is_one_line(
        probe: Probe, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """CameraInfo that OpenCV would refuse (6 plumb_bob coefficients, fx 1e308, D 1e10) is
    rejected by the camera model's door with its reason, not a cv2.error on the first frame; a
    bag without any CameraInfo says so."""
    cases = [({"d": [0.1, 0, 0, 0, 0, 0.2], "distortion_model": "plumb_bob"},
              "plumb_bob takes 5 coefficients"),
             ({"k": [1e308, 0, 479.5, 0, 1e308, 269.5, 0, 0, 1]}, "are not sane"),
             ({"d": [1e10, 0, 0, 0, 0], "distortion_model": "plumb_bob"}, "exceed 1000")]
    for i, (fields, says) in enumerate(cases):
        bag = jpeg_bag(tmp_path / f"bad{i}", probe.jpegs[:2], camera_info_with(probe.camera,
                                                                               **fields))
        line = _case(probe, tmp_path, ["replay", bag, "--out", tmp_path / f"o{i}"], 1, says,
                     capsys=capsys)
        assert "holds no valid CameraInfo (2 refused, the first: " in line
    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.io.sources import CAMERA_INFO_TYPE, COMPRESSED_TYPE

    with BagWriter(tmp_path / "no_info") as w:  # the topic, but not one message on it
        w.add_topic("/cam/image_raw/compressed", COMPRESSED_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        w.write("/cam/image_raw/compressed", 1, messages.compressed_image(
            ROSBAGS, messages.header(ROSBAGS, 1, "cam"), probe.jpegs[0]))
    _case(probe, tmp_path, ["replay", tmp_path / "no_info", "--out", tmp_path / "o"], 1,
          "holds no CameraInfo message", capsys=capsys)


def test_probe_memory_is_checked_before_it_is_spent(probe: Probe, tmp_path: Path) -> None:
    """A 30000x30000 JPEG header is refused before decoding (replay labels the frame, detect
    says so); a cut sqlite3 bag of 1 GB and an MCAP whose chunk claims a terabyte are salvaged
    without reading them whole: each within the memory bound."""
    huge = huge_jpeg_header()
    bag = jpeg_bag(tmp_path / "huge", [probe.jpegs[0], huge, probe.jpegs[1]], probe.camera)
    _case(probe, tmp_path, ["replay", bag, "--out", tmp_path / "o1"], 0, "1 skipped")
    reasons = read_labels(tmp_path / "o1").reasons
    assert "JPEG image is 30000x30000 (900.0 MP), above the 40.0 MP budget" in reasons[1]
    (tmp_path / "huge.jpg").write_bytes(huge)
    _case(probe, tmp_path, ["detect", tmp_path / "huge.jpg"], 1, "30000x30000")

    # A 1 GB sqlite3 bag cut short: its header counts 2 GB of pages (sparse: no disk used).
    small_bag(tmp_path / "sq", "sqlite3", n=10)
    db = next((tmp_path / "sq").glob("*.db3"))
    with open(db, "r+b") as handle:
        handle.seek(28)
        handle.write((1 << 19).to_bytes(4, "big"))
    extend_sparse(db, (1 << 30) + 100)
    _case(probe, tmp_path, ["replay", tmp_path / "sq", "--out", tmp_path / "o2"], 3, "cut short")

    small_bag(tmp_path / "mc", "mcap", n=10)
    data = next((tmp_path / "mc").glob("*.mcap"))
    raw = bytearray(data.read_bytes())
    chunk = raw.index(b"\x06", 8 + 9 + int.from_bytes(raw[9:17], "little"))  # the first chunk
    raw[chunk + 1: chunk + 9] = (1 << 40).to_bytes(8, "little")
    data.write_bytes(bytes(raw))
    extend_sparse(data, 1 << 30)
    _case(probe, tmp_path, ["replay", tmp_path / "mc", "--out", tmp_path / "o3"], 3,
          "claims 1099511627776 bytes")


def test_probe_cut_recordings_commit_nothing_and_say_what_was_lost(
        probe: Probe, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A 1 % cut MCAP holds no whole frame: exit 1 in one line that says what was lost (in
    recording time, never an epoch as seconds), and no output folder at all."""
    cut = tmp_path / "cut"
    cut.mkdir()
    for f in probe.bag.iterdir():
        data = f.read_bytes()
        (cut / f.name).write_bytes(data[: max(len(data) // 100, 40)] if f.suffix == ".mcap"
                                   else data)
    line = _case(probe, tmp_path, ["replay", cut, "--out", tmp_path / "o"], 1, "", capsys=capsys)
    assert "1700000000" not in line
    assert not (tmp_path / "o").exists()
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".rss")) == ["cut"]


def test_probe_outputs_that_are_odd_places(
        probe: Probe, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A symbolic-link loop or an immutable folder as --out fails before any processing; --out
    as a link to an empty folder writes there and leaves no link behind; FICAP_MAX_PIXELS as a
    float is a number, as a word an error."""
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    _case(probe, tmp_path, ["replay", probe.bag, "--out", loop], 1, "leads nowhere",
          capsys=capsys)
    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "link").symlink_to(real, target_is_directory=True)
    _case(probe, tmp_path, ["replay", probe.bag, "--out", tmp_path / "link"], 0, "frames",
          capsys=capsys)
    assert (real / "labels.csv").exists()
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".rss")) == [
        "link", "loop", "real"]
    frozen = tmp_path / "frozen"
    frozen.mkdir()
    if subprocess.run(["chattr", "+i", str(frozen)], capture_output=True).returncode == 0:
        try:
            _case(probe, tmp_path, ["replay", probe.bag, "--out", frozen], 1, "immutable",
                  capsys=capsys)
        finally:
            subprocess.run(["chattr", "-i", str(frozen)], check=True)
    (tmp_path / "f.jpg").write_bytes(probe.jpegs[0])
    _case(probe, tmp_path, ["detect", tmp_path / "f.jpg"], 1, "above the 0.0 MP budget",
          env={"FICAP_MAX_PIXELS": "1e3"}, capsys=capsys)
    _case(probe, tmp_path, ["detect", tmp_path / "f.jpg"], 1, "FICAP_MAX_PIXELS='lots'",
          env={"FICAP_MAX_PIXELS": "lots"}, capsys=capsys)


def test_probe_manifest_entries_never_write_outside_out(
        probe: Probe, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``../in/bag`` in a manifest: its output goes under --out by its name; the ficap output
    folder beside the input (what a mirrored path would have replaced) is untouched."""
    inputs = tmp_path / "in"
    shutil.copytree(probe.bag, inputs / "bag")
    other = tmp_path / "in" / "labels_of_before"
    other.mkdir()
    (other / "labels.csv").write_text("frame\n")
    lists = tmp_path / "lists"
    lists.mkdir()
    (lists / "manifest.txt").write_text("../in/bag\n")
    before = sha256s([inputs])
    out = tmp_path / "out"
    _case(probe, tmp_path, ["replay", "--manifest", lists / "manifest.txt", "--out", out], 0,
          "1 recordings: 1 done", capsys=capsys)
    assert sha256s([inputs]) == before and (out / "labels.csv").is_file()
    (lists / "manifest.txt").write_text(f"../in/bag\n{tmp_path}/in/bag\n")
    _case(probe, tmp_path, ["replay", "--manifest", lists / "manifest.txt", "--out", out], 1,
          "would both write to bag", capsys=capsys)
    assert sha256s([inputs]) == before


def test_probe_damaged_jpegs_are_never_labelled_with_confidence(
        probe: Probe, tmp_path: Path, rendered_frames) -> None:  # noqa: ANN001
    """Ten JPEGs with 50 bytes of their entropy-coded data changed (libjpeg decodes them anyway
    and only warns), between the good frames they came from: no frame gets a pose off by more
    than its 95 % bound without a damage reason; every good frame keeps its pose."""
    from scipy.spatial.transform import Rotation

    from ficap_ros.tools import synth

    _, scene = rendered_frames
    truth = [f.T_cam_cap.rotation for f in synth.naturalistic_drive(CORRUPT_BAG_FRAMES, 30.0, 5,
                                                                     scene)]
    sources = list(range(CORRUPT_BAG_FRAMES)) * 2
    damaged = [flip_bytes(probe.jpegs[i], 50, seed) for seed, i in enumerate(sources)]
    jpegs = probe.jpegs + damaged
    bag = jpeg_bag(tmp_path / "flipped", jpegs, probe.camera)
    _case(probe, tmp_path, ["replay", bag, "--out", tmp_path / "o"], 0, "10 skipped")
    labels = read_labels(tmp_path / "o")
    rows = list(csv.reader((tmp_path / "o" / "labels.csv").open()))[1:]
    source = list(range(CORRUPT_BAG_FRAMES)) + sources
    flagged = 0
    for row, (k, has_pose) in enumerate(zip(source, labels.has_pose)):
        reason = labels.reasons[row]
        if row < CORRUPT_BAG_FRAMES:
            assert has_pose, rows[row]  # a good frame is never taken for damaged
            continue
        flagged += "damaged JPEG" in reason
        if has_pose:
            q = labels.q_cam_cap_wxyz[row]
            error = np.degrees((Rotation.from_quat(q[[1, 2, 3, 0]]) * truth[k].inv()).magnitude())
            assert error <= labels.rot_err95_deg[row] or "damaged" in reason, rows[row]
    assert flagged == 10


def test_every_output_flag_pointed_at_an_input_leaves_it_unchanged(
        probe: Probe, tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Each verb's output flag at an input itself, the folder holding it, its (or its folder's)
    metadata.yaml and a path inside an input folder: refused in one line before anything is
    read, and every input byte unchanged (a manifest's way outside --out: the manifest case
    above)."""
    monkeypatch.chdir(tmp_path)
    before = sha256s(probe.inputs())
    refused = 0
    for name, argv, target in walk_cases(probe):
        folder = target if target.is_dir() else target.parent
        outs = [target, target.parent] + [m for m in [folder / "metadata.yaml"] if m.exists()]
        if target.is_dir():
            outs.append(target / "inside" / "x")
        for out in outs:
            code = main([str(out) if a == "OUT" else a for a in argv])
            err = capsys.readouterr().err.strip().splitlines()
            assert code == 1, (name, out, code, err)
            assert len(err) == 1 and err[0].startswith("ficap: error:"), (name, out, err)
            assert "Traceback" not in err[0]
            refused += 1
        assert sha256s(probe.inputs()) == before, name
    assert refused >= 3 * len(walk_cases(probe))
    assert not (tmp_path / "m.yaml").exists()
