"""A labels.csv of a known head motion, and an estimator of it with a known error: what the
evaluation's tests (test/tools/test_evaluation.py, test/cli/test_evaluate.py) measure."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.metrics import rotation_from_ypr_deg
from ficap_ros.geometry.transform import Transform
from ficap_ros.io.labels import FrameRecord, labels_csv_text
from ficap_ros.vision.calibration import HeadCalibration
from ficap_ros.vision.pose import CapPose

N = 400
FPS = 30.0
T0_NS = 1_700_000_000_000_000_000
YAW_OFFSET_DEG = 3.0
NOISE_DEG = 0.3


def truth_labels(tmp_path: Path) -> tuple[Path, Rotation, np.ndarray]:
    """labels.csv of a random head motion (cap = head, R_cam_frontal default), every 5th without pose."""
    rng = np.random.default_rng(7)
    ypr = np.column_stack([rng.uniform(-50, 50, N), rng.uniform(-20, 15, N), rng.uniform(-8, 8, N)])
    R_frontal_head = Rotation.from_euler("ZYX", ypr * [1, -1, 1], degrees=True)
    cal = HeadCalibration()
    stamps = T0_NS + np.round(np.arange(N) * 1e9 / FPS).astype(np.int64)
    records = []
    for i in range(N):
        if i % 5 == 4:
            records.append(FrameRecord.processed(i, int(stamps[i]), "cam", None, (), "no tag", cal))
            continue
        R_cam_cap = cal.R_cam_frontal * R_frontal_head[i]
        pose = CapPose(Transform(R_cam_cap, [0.0, 0.1, 0.5]), 6, 6, (1, 2, 3, 4, 5, 6), 0.3,
                       np.eye(6) * 1e-6, 0.9, "joint")
        records.append(FrameRecord.processed(i, int(stamps[i]), "cam", pose, (1, 2, 3, 4, 5, 6), "", cal))
    path = tmp_path / "labels.csv"
    path.write_text(labels_csv_text(records))
    return path, R_frontal_head, stamps


def estimate_of(R_truth: Rotation, seed: int = 3) -> Rotation:
    """Truth turned by a constant yaw offset (about F's z) plus isotropic noise."""
    rng = np.random.default_rng(seed)
    noise = Rotation.from_rotvec(np.radians(rng.normal(0.0, NOISE_DEG, (len(R_truth), 3))))
    return noise * rotation_from_ypr_deg(YAW_OFFSET_DEG, 0.0, 0.0) * R_truth
