"""ficap_ros.ros.demo: a ``ficap synth`` recording read back (images, intrinsics, truth in stamp
order), then played into a live ficap_node over real topics: calibrated at the end of its frontal
segment, every frame answered, the head pose after calibration within a degree of the truth."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from recordings import small_bag

from ficap_ros.cli.synth import START_NS, write_synth_bag
from ficap_ros.errors import BagError
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.ros.demo import load_recording, run_demo
from ficap_ros.tools.synth import default_scene, naturalistic_drive

#: A short sample drive: 640x360, 1.8 s at 30 fps, looking ahead for the first 1.5 s (enough
#: frames for the node's frontal calibration: 30 in its window), then 9 frames after it.
FRAMES, FPS, FRONTAL_S, SEED = 54, 30.0, 1.5, 2


@pytest.fixture(scope="module")
def sample(tmp_path_factory: pytest.TempPathFactory) -> Path:
    bag = tmp_path_factory.mktemp("demo") / "sample"
    write_synth_bag(bag, nominal_model(), resolution=(640, 360), frames=FRAMES, fps=FPS, seed=SEED,
                    frontal_s=FRONTAL_S, progress=False)
    return bag


def test_the_recording_reads_back_in_stamp_order_with_its_truth(sample: Path) -> None:
    recording = load_recording(sample)
    drive = naturalistic_drive(FRAMES, fps=FPS, seed=SEED, scene=default_scene((640, 360)),
                               frontal_s=FRONTAL_S)
    assert [r.stamp_ns for r in recording] == [START_NS + f.stamp_ns for f in drive]
    camera = default_scene((640, 360)).camera
    for rec, truth in zip(recording, drive):
        assert rec.jpeg[:2] == b"\xff\xd8"  # the JPEG as recorded
        assert (rec.info["width"], rec.info["height"]) == (640, 360)
        np.testing.assert_allclose(np.reshape(rec.info["k"], (3, 3)), camera.K)
        assert angle_deg(rec.R_frontal_head, truth.R_frontal_head) < 1e-6


def test_a_recording_without_its_topics_is_refused(tmp_path: Path) -> None:
    small_bag(tmp_path / "raw", "mcap", n=2)  # raw images on /cam/image_raw, no compressed topic
    with pytest.raises(BagError, match="no /camera/image_raw/compressed topic"):
        load_recording(tmp_path / "raw")


def test_the_demo_calibrates_and_follows_the_truth(sample: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert run_demo(sample, frontal_s=FRONTAL_S, every=6) == 0
    out = capsys.readouterr().out
    assert f"ficap demo: {FRAMES} frames of the sample drive" in out
    assert re.search(r"~/calibrate -> success=True: calibrated \(frontal\) from (3\d|4\d) frames",
                     out), out
    assert f"frames: {FRAMES}, with head pose: {FRAMES}," in out
    rows = [ln for ln in out.splitlines() if re.match(r"\s+\d+\.\d\d\s+\d+\s+\d+", ln)]
    assert len(rows) == FRAMES // 6  # every 6th frame printed
    before = [float(r.split()[-2]) for r in rows if r.endswith("(uncalibrated)")]
    # Uncalibrated, the head pose is the cap's: off by how the cap sits on the head (~10 deg).
    assert len(before) == 8 and min(before) > 5.0
    median = float(re.search(r"after calibration, geodesic: mean \S+  median (\S+)", out).group(1))
    assert median < 1.0
    assert "over 9 frames" in out
