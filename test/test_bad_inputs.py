"""Bad inputs against every reader and verb that takes them: the corpus (test/data/bad_inputs,
written by test/helpers/make_bad_inputs.py), files that are not text, and random and damaged files
(hypothesis). Each gives a one-line error, a recovered result or a labelled skip, never a
traceback.

It mirrors no module of ficap_ros (test_package.py's ``UNMIRRORED`` says why): bad inputs cross
every reader and verb, and one corpus serves them all.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from mutations import mutated
from recordings import one_error_line

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
    # libjpeg decodes a JPEG cut short with the missing rows grey (and a throttled warning).
    expected = {"tags_duplicated_ids.png": 0, "tags_foreign_ids.png": 0, "jpeg_truncated.jpg": 0}
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


def test_node_starts_or_refuses_in_one_line_on_every_bad_file() -> None:
    """The node's three file parameters with every bad YAML of the corpus (real rclpy)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from ficap_ros.ros.node import FicapNode

    context = Context()
    rclpy.init(context=context)
    try:
        for param, files, fatal in (("camera_info_file", INTRINSICS, False),
                                    ("calibration.file", CALIBRATIONS, False),
                                    ("model_file", MODELS, True)):
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
    assert np.isfinite(0.0)


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
