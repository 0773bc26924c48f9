"""ficap stats: counts from a bag with a corrupt frame, from labels (the same as the replay's summary)
and from a cut recording; a half-written CSV row dropped; a text file called neither bag nor video."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from recordings import CORRUPT_BAG_FRAMES as N
from recordings import FRAMES, cut_copy

from ficap_ros.cli.args import EXIT_FRAMES_LOST
from ficap_ros.cli.main import main
from ficap_ros.io.labels import read_labels


def test_stats_from_bag(bag_with_a_corrupt_frame: Path, tmp_path: Path,
                        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["stats", str(bag_with_a_corrupt_frame), "--out", str(tmp_path), "--quiet"]) == 0
    d = json.loads((tmp_path / "stats.json").read_text())
    assert d["frames"] == N - 1 and d["frames_skipped"] == 1
    assert d["frames_ge4_tags"] == N - 1 and d["frames_no_tag"] == 0
    assert max(d["tag_detection_rate"].values()) == 1.0
    assert (tmp_path / "tag_detection_rate.png").exists()
    assert ">=4 tags" in capsys.readouterr().out


def test_a_text_file_is_called_neither_a_bag_nor_a_video(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`ficap stats notes.txt` says the file is neither a bag nor a video, not that a video needs
    --intrinsics; a real video without --intrinsics asks for them."""
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


def test_stats_from_labels_and_bag_agree(drive: Path, replayed_calibrated: Path, tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["stats", str(replayed_calibrated), "--out", str(tmp_path / "s1")]) == 0
    from_labels = json.loads((tmp_path / "s1" / "stats.json").read_text())
    summary = json.loads((replayed_calibrated / "summary.json").read_text())
    assert from_labels["frames"] == summary["frames"]
    assert from_labels["frames_ge4_tags"] == summary["frames_ge4_tags"]
    assert sum(from_labels["reliability_histogram"]["counts"]) == summary["frames_with_pose"]
    rates = from_labels["tag_detection_rate"]
    assert len(rates) == 23 and all(0.0 <= v <= 1.0 for v in rates.values())
    labels = read_labels(replayed_calibrated)
    assert sum(rates.values()) * FRAMES == pytest.approx(labels.tags_detected.sum())
    assert (tmp_path / "s1" / "reliability_histogram.png").read_bytes()[:4] == b"\x89PNG"


def test_stats_drops_a_half_written_csv_row(replayed: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    text = (replayed / "labels.csv").read_text()
    cut = tmp_path / "labels.csv"
    cut.write_text(text[: len(text) - 40])  # the last row loses its end
    assert len(read_labels(cut).stamp_ns) == FRAMES - 1
    assert main(["stats", str(cut)]) == 0
    assert capsys.readouterr().out.startswith(f"frames {FRAMES - 1} ")


def test_stats_reads_a_cut_mcap(drive: Path, tmp_path: Path,
                                capsys: pytest.CaptureFixture[str]) -> None:
    cut = cut_copy(drive, tmp_path / "cut", 0.9)
    assert main(["stats", str(cut), "--quiet"]) == EXIT_FRAMES_LOST
    assert "LOST" in capsys.readouterr().out
