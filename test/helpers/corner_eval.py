"""Corner accuracy on rendered frames with exact ground truth, shared by test_corners.py and
test_photometric.py (not a test module: no ``test_`` prefix)."""

from __future__ import annotations

import numpy as np

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import corner_errors_px
from ficap_ros.tools.synth import (
    RenderConfig,
    RenderedFrame,
    default_scene,
    naturalistic_drive,
    render,
)
from ficap_ros.vision.detector import TagDetector
from ficap_ros.vision.tracking import view_angles_deg

MODEL = nominal_model()


def drive_frames(resolution: str, config: RenderConfig, n: int = 3) -> list[RenderedFrame]:
    """``n`` frames of a naturalistic drive (seed 5, one a second), rendered with ``config``."""
    scene = default_scene(resolution)
    drive = naturalistic_drive(n, fps=1.0, seed=5, scene=scene, frontal_s=0.0)
    return [render(MODEL, scene.camera, d.T_cam_cap, config, seed=d.index) for d in drive]


def clean_corner_errors(detector: TagDetector, frames: list[RenderedFrame]
                        ) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(corner errors px, radial offsets px, clean tags found, clean tags) over the frames.

    Clean tags are issue 10's: fully visible and within 70 deg of head-on."""
    err, rad, found_n, clean_n = [], [], 0, 0
    for fr in frames:
        angles = dict(zip(MODEL.ids, view_angles_deg(MODEL, fr.T_cam_cap)))
        clean = [t for t in fr.visible_ids(0.999) if angles[t] <= 70.0]
        found = {d.tag_id: d.corners_px for d in detector.detect(fr.image)}
        ids = [t for t in clean if t in found]
        e, r = corner_errors_px(np.array([found[t] for t in ids]), np.array([fr.corners_px[t] for t in ids]))
        err.append(e.ravel())
        rad.append(r.ravel())
        found_n += len(ids)
        clean_n += len(clean)
    return np.concatenate(err), np.concatenate(rad), found_n, clean_n
