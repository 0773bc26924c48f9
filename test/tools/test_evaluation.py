"""ficap_ros.tools.evaluation: head orientations read from CSV and bags, paired by stamp and
compared (geodesic angle, the paper's Phi3, per-axis errors wrapped), the report, and the
detection statistics with their reliability histogram."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from head_series import N, truth_labels
from scipy.spatial.transform import Rotation

from ficap_ros.errors import BagError
from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.stamps import pair_by_stamp
from ficap_ros.tools import evaluation
from ficap_ros.tools.evaluation import (
    PoseSeries,
    evaluate,
    load_series,
    read_series_csv,
)


def test_labels_truth_round_trip(tmp_path: Path) -> None:
    path, R, stamps = truth_labels(tmp_path)
    series = load_series(str(path))
    keep = np.arange(N) % 5 != 4
    assert len(series) == keep.sum()
    np.testing.assert_array_equal(series.stamp_ns, stamps[keep])
    err = np.degrees((series.rotations.inv() * R[keep]).magnitude())
    assert err.max() < 1e-5


def test_evaluate_zero_error_and_dt_gate(tmp_path: Path) -> None:
    truth_csv, R, stamps = truth_labels(tmp_path)
    truth = load_series(str(truth_csv))
    res = evaluate(truth, truth, max_dt_ms=1.0)
    assert res.n_paired == len(truth) and float(res.geodesic_deg.max()) < 1e-5
    i_t, i_e = pair_by_stamp(np.array([0, 100, 200]), np.array([5, 130, 131, 400]), 20)
    assert i_t.tolist() == [0] and i_e.tolist() == [0]


def test_reliability_histogram_labels_each_bar_with_its_frames(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The bars are a density (bins differ in width), so 30 frames in one 0.02 bin stand 1500
    high: each non-empty bar is labelled with its frame count, and the title gives the totals."""

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


def _csv(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_csv_columns_head_first_then_plain_then_angles(tmp_path: Path) -> None:
    """head_q* wins over q*; angles when no quaternion; rows without an orientation skipped;
    stamps sorted; zero or non-finite quaternions dropped."""
    q = Rotation.from_euler("z", 30.0, degrees=True).as_quat()  # x, y, z, w
    both = _csv(tmp_path / "both.csv",
                "stamp_ns,qw,qx,qy,qz,head_qw,head_qx,head_qy,head_qz\n"
                f"20,1,0,0,0,{q[3]},{q[0]},{q[1]},{q[2]}\n"
                "10,1,0,0,0,,,,\n"
                f"5,1,0,0,0,{q[3]},{q[0]},{q[1]},{q[2]}\n"
                "7,1,0,0,0,0,0,0,0\n"
                "8,1,0,0,0,nan,0,0,0\n")
    s = read_series_csv(both)
    assert s.stamp_ns.tolist() == [5, 20] and s.source == str(both)
    assert np.degrees(s.rotations.magnitude()) == pytest.approx([30.0, 30.0])
    angles = _csv(tmp_path / "angles.csv", "stamp_ns,yaw_deg,pitch_deg,roll_deg\n3,10,-5,2\n4,,,\n")
    s = read_series_csv(angles)
    assert s.stamp_ns.tolist() == [3]
    assert np.degrees((s.rotations[0].inv() * rotation_from_ypr_deg(10, -5, 2)).magnitude()) < 1e-9
    for text, says in (("qw,qx,qy,qz\n1,0,0,0\n", "has no stamp_ns column"),
                       ("stamp_ns,w,x,y,z\n1,1,0,0,0\n", "has neither qw,qx,qy,qz nor"),
                       ("stamp_ns,qw,qx,qy,qz\n1,,,,\n", "holds no head orientation"),
                       ("stamp_ns,qw,qx,qy,qz\n1,0,0,0,0\n", "holds no valid orientation")):
        with pytest.raises(BagError, match=says):
            read_series_csv(_csv(tmp_path / "bad.csv", text))


def test_bag_series_and_what_a_spec_means(tmp_path: Path) -> None:
    from ficap_ros.geometry.transform import Transform
    from ficap_ros.io import messages
    from ficap_ros.io.bag_writer import BagWriter
    from ficap_ros.io.messages import ROSBAGS

    bag = tmp_path / "est"
    R = [rotation_from_ypr_deg(float(k), 0.0, 0.0) for k in range(3)]
    with BagWriter(bag) as w:
        w.add_topic("/head", "geometry_msgs/msg/PoseStamped")
        w.add_topic("/image", "sensor_msgs/msg/Image")
        for k, r in enumerate(R):
            stamp = 1000 + k
            w.write("/head", 5_000 + k,  # log time differs: the header's stamp counts
                    messages.pose_stamped(ROSBAGS, messages.header(ROSBAGS, stamp, "f"),
                                          Transform(r, np.zeros(3))))
    s = load_series(f"{bag}:/head")
    assert s.stamp_ns.tolist() == [1000, 1001, 1002] and s.source == f"{bag}:/head"
    assert np.degrees(s.rotations.magnitude()) == pytest.approx([0.0, 1.0, 2.0])
    with pytest.raises(BagError, match=r"has no topic /nope \(pose topics: /head\)"):
        load_series(f"{bag}:/nope")
    with pytest.raises(BagError, match="is sensor_msgs/msg/Image, not one of PoseStamped"):
        load_series(f"{bag}:/image")
    odd = _csv(tmp_path / "a:b.csv", "stamp_ns,yaw_deg,pitch_deg,roll_deg\n1,0,0,0\n")
    assert len(load_series(str(odd))) == 1  # a colon in a file name is no topic
    with pytest.raises(BagError, match="does not exist"):
        load_series(str(tmp_path / "none.csv"))


def _series(stamps: list[int], ypr_deg: list[tuple[float, float, float]]) -> PoseSeries:
    return PoseSeries(np.array(stamps, np.int64),
                      Rotation.concatenate([rotation_from_ypr_deg(*a) for a in ypr_deg]), "s")


def test_errors_of_a_known_offset_and_the_yaw_wrap() -> None:
    """An estimate 10 deg of yaw off: geodesic 10, Phi3 5 (half), yaw error +10 also across
    +-180 deg, pitch and roll 0; truth stamps unmatched within the tolerance stay unpaired."""
    truth = _series([0, 100, 200, 300], [(0, 0, 0), (175, 0, 0), (-50, 0, 0), (0, 0, 0)])
    est = _series([3, 98, 205, 900], [(10, 0, 0), (-175, 0, 0), (-40, 0, 0), (0, 0, 0)])
    res = evaluate(truth, est, max_dt_ms=1e-5)  # 10 ns
    assert res.n_paired == 3 and res.stamp_ns.tolist() == [0, 100, 200]
    np.testing.assert_allclose(res.geodesic_deg, 10.0, atol=1e-9)
    np.testing.assert_allclose(res.phi3_deg, 5.0, atol=1e-9)
    np.testing.assert_allclose(res.axis_error_deg, [[10, 0, 0]] * 3, atol=1e-9)
    s = res.summary()
    assert (s["n_truth"], s["n_estimate"], s["n_paired"]) == (4, 4, 3)
    assert s["pct_truth_paired"] == 75.0 and s["axis_error_deg"]["yaw"]["rmse"] == pytest.approx(10.0)
    assert s["geodesic_deg"]["median"] == pytest.approx(10.0)
    with pytest.raises(BagError, match="no estimate within 0.001 ms"):
        evaluate(truth, _series([10**9], [(0, 0, 0)]), max_dt_ms=0.001)


def test_the_report_files(tmp_path: Path) -> None:
    truth = _series([0, 1], [(0, 0, 0), (20, 0, 0)])
    res = evaluate(truth, _series([0, 1], [(0, 0, 3), (20, 0, 3)]), max_dt_ms=1.0)
    paths = evaluation.write_report(res, tmp_path / "r", plots=False)
    assert [p.name for p in paths] == ["report.md", "report.json"]
    data = json.loads((tmp_path / "r" / "report.json").read_text())
    assert data["n_paired"] == 2 and data["axis_error_deg"]["roll"]["mean"] == pytest.approx(3.0)
    md = (tmp_path / "r" / "report.md").read_text()
    assert "| geodesic angle | 3.000 | 3.000 |" in md and "| roll | +3.000 |" in md
    assert evaluation._finite({"a": math.nan, "b": {"c": math.inf, "d": 1.5}}) == \
        {"a": None, "b": {"c": None, "d": 1.5}}


def test_detection_counts_rates_and_histogram() -> None:
    tags = np.array([0, 1, 4, 6, 9, 3])
    ids = ((), (1,), (1, 2, 3, 4), (1, 2, 3, 4, 5, 5, 99), (), (1, 2, 3))
    rel = np.array([np.nan, np.nan, 0.85, 1.0, np.nan, 0.05])
    has_pose = np.isfinite(rel)
    skipped = np.array([False, False, False, False, True, False])
    st = evaluation.detection_stats(tags, ids, rel, has_pose, skipped, (1, 2, 3, 4, 5, 6))
    assert (st.frames, st.frames_skipped, st.frames_no_tag) == (5, 1, 1)
    assert (st.frames_ge1_tag, st.frames_ge4_tags, st.frames_with_pose) == (4, 2, 3)
    assert st.tag_rate == {1: 0.8, 2: 0.6, 3: 0.6, 4: 0.4, 5: 0.2, 6: 0.0}  # 5 twice: once
    assert st.reliability_counts.sum() == 3
    assert st.reliability_counts[0] == 1 and st.reliability_counts[-1] == 1  # 1.0 in the last bin
    assert st.reliability_counts[np.searchsorted(st.reliability_edges, 0.85) - 1] == 1
    d = st.to_dict()
    assert d["pct_ge4_tags"] == 40.0 and d["tag_detection_rate"]["1"] == 0.8
    assert len(d["reliability_histogram"]["edges"]) == len(d["reliability_histogram"]["counts"]) + 1
