"""ficap stats / replay on a small rendered bag with one corrupt frame, and on a video."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ficap_ros.cli.main import main
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.io import messages
from ficap_ros.io.bag_writer import BagWriter
from ficap_ros.io.labels import read_labels
from ficap_ros.io.messages import ROSBAGS
from ficap_ros.io.sources import CAMERA_INFO_TYPE, COMPRESSED_TYPE
from ficap_ros.tools import synth

N = 5
BAD = 2
T0 = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def rendered() -> tuple[list[np.ndarray], synth.DriveScene]:
    scene = synth.default_scene("540p")
    drive = synth.naturalistic_drive(N, 30.0, 5, scene)
    model = nominal_model()
    return [synth.render(model, scene.camera, f.T_cam_cap, seed=f.index).image for f in drive], scene


@pytest.fixture(scope="module")
def bag(rendered, tmp_path_factory: pytest.TempPathFactory) -> Path:  # noqa: ANN001
    images, scene = rendered
    path = tmp_path_factory.mktemp("bags") / "drive.mcap"
    with BagWriter(path, storage="mcap", layout="file") as w:
        w.add_topic("/cam/image/compressed", COMPRESSED_TYPE)
        w.add_topic("/cam/camera_info", CAMERA_INFO_TYPE)
        for i, img in enumerate(images):
            s = T0 + i * 33_333_333
            head = messages.header(ROSBAGS, s, "cam")
            w.write("/cam/camera_info", s, messages.camera_info(ROSBAGS, head, scene.camera))
            data = cv2.imencode(".jpg", img)[1].tobytes() if i != BAD else b"\xff\xd8 truncated"
            w.write("/cam/image/compressed", s, messages.compressed_image(ROSBAGS, head, data))
    return path


def test_replay_counts_the_corrupt_frame(bag: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    assert main(["replay", str(bag), "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == N and summary["frames_skipped"] == 1
    assert summary["frames_with_pose"] == N - 1
    assert sum(summary["skipped_reasons"].values()) == 1
    labels = read_labels(out)
    assert len(labels) == N  # one row per image, the corrupt one without pose fields
    assert labels.skipped.tolist() == [i == BAD for i in range(N)]
    assert not labels.has_pose[BAD] and labels.has_pose.sum() == N - 1
    row = (out / "labels.csv").read_text().splitlines()[1 + BAD].split(",")
    assert row[6:20] == [""] * 14 and row[-1].startswith("undecodable")


def test_stats_from_bag(bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["stats", str(bag), "--out", str(tmp_path), "--quiet"]) == 0
    d = json.loads((tmp_path / "stats.json").read_text())
    assert d["frames"] == N - 1 and d["frames_skipped"] == 1
    assert d["frames_ge4_tags"] == N - 1 and d["frames_no_tag"] == 0
    assert max(d["tag_detection_rate"].values()) == 1.0
    assert (tmp_path / "tag_detection_rate.png").exists()
    assert ">=4 tags" in capsys.readouterr().out


def test_replay_video(rendered, tmp_path: Path) -> None:  # noqa: ANN001
    images, scene = rendered
    video = tmp_path / "drive.avi"
    w, h = scene.camera.width_px, scene.camera.height_px
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (w, h))
    for img in images:
        writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    writer.release()
    intr = tmp_path / "camera.yaml"
    intr.write_text(yaml.safe_dump(scene.camera.to_camera_yaml()))
    out = tmp_path / "out"
    assert main(["replay", str(video), "--intrinsics", str(intr), "--fps", "30", "--out",
                 str(out), "--quiet"]) == 0
    labels = read_labels(out)
    assert len(labels) == N and labels.has_pose.all()
    assert labels.stamp_ns[1] == 33_333_333
    assert main(["replay", str(video), "--out", str(out), "--quiet"]) == 1  # no intrinsics


def test_reliability_histogram_labels_each_bar_with_its_frames(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The bars are a density (bins differ in width), so 30 frames in one 0.02 bin stand 1500
    high: each non-empty bar is labelled with its frame count, and the title gives the totals."""
    from ficap_ros.tools import evaluation

    reliability = np.array([0.55] * 3 + [0.99] * 30 + [np.nan] * 2)
    stats = evaluation.detection_stats(
        np.array([5] * 33 + [0, 0]), tuple((1, 2, 3, 4, 5) for _ in range(33)) + ((), ()),
        reliability, np.isfinite(reliability), np.zeros(35, dtype=bool), tuple(range(23)))
    figures = {}

    def keep(fig, path):  # noqa: ANN001, ANN202
        figures[path.name] = fig
        return path

    monkeypatch.setattr(evaluation, "_png", keep)
    evaluation.plot_stats(stats, tmp_path)
    ax = figures["reliability_histogram.png"].axes[0]
    assert sorted(t.get_text() for t in ax.texts) == ["3", "30"]
    assert "33 frames with a pose of 35" in ax.get_title()
    assert "35 frames" in figures["tag_detection_rate.png"].axes[0].get_title()


def test_a_text_file_is_called_neither_a_bag_nor_a_video(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`ficap stats notes.txt` was 'video notes.txt needs --intrinsics': it is no video. A real
    video without --intrinsics still asks for them."""
    notes = tmp_path / "notes.txt"
    notes.write_text("not a recording\n")
    video = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48))
    for _ in range(3):
        writer.write(np.zeros((48, 64, 3), np.uint8))
    writer.release()
    for path, says in ((notes, f"{notes} is neither a bag"),
                       (video, f"video {video} needs --intrinsics")):
        assert main(["stats", str(path), "--quiet"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("ficap: error:"), err
        assert says in err[0] and "needs --intrinsics" not in err[0].replace(says, ""), err
