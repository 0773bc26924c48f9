"""ficap_ros.tools.model_build.observations: which frames the adjustment uses (enough distinct model
tags, an initial pose from the nominal model, at most ``max_frames`` spread evenly), the flat
observation arrays, and whether the frames cover and link every tag."""

from __future__ import annotations

import numpy as np
import pytest
from cap_views import CAMERA, observe

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.tools.model_build import BuildConfig, CoverageError
from ficap_ros.tools.model_build.observations import (
    _candidates,
    coverage_problems,
    ids_per_frame,
    problem_from,
    usable_frames,
)
from ficap_ros.vision.detector import TagDetection

NOMINAL = nominal_model()


@pytest.fixture(scope="module")
def views():
    """Eight exact views (no noise) of the nominal cap: (T_cam_cap, detections) each."""
    return observe(NOMINAL, count=8, seed=31, noise_px=0.0)


def test_candidates_drop_doubled_and_foreign_ids_and_thin_out_evenly(views) -> None:
    dets = list(views[0][1])
    doubled = dets + [TagDetection(dets[0].tag_id, dets[0].corners_px + 5.0),
                      TagDetection(999, dets[1].corners_px)]
    [(index, kept)] = _candidates([doubled], NOMINAL, BuildConfig())
    assert index == 0 and sorted(d.tag_id for d in kept) == sorted(d.tag_id for d in dets[1:])
    few = [d for d in dets[:3]]
    assert _candidates([few], NOMINAL, BuildConfig()) == []
    assert len(_candidates([few], NOMINAL, BuildConfig(min_tags_per_frame=3))) == 1
    frames = [dets] * 10
    picked = [i for i, _ in _candidates(frames, NOMINAL, BuildConfig(max_frames=4))]
    assert picked == [0, 3, 6, 9]


def test_usable_frames_start_from_the_nominal_pose(views) -> None:
    said: list[str] = []
    used = usable_frames([d for _, d in views], [CAMERA] * len(views), NOMINAL, BuildConfig(),
                         said.append)
    assert [u[0] for u in used] == list(range(len(views)))
    assert said == [f"{len(views)} of {len(views)} frames see >= 4 tags"]
    for (index, T, dets), (T_true, true_dets) in zip(used, views):
        assert 1000.0 * np.linalg.norm(T.translation_m - T_true.translation_m) < 0.1
        assert {d.tag_id for d in dets} == {d.tag_id for d in true_dets}  # all pose inliers
    with pytest.raises(CoverageError, match=r"only 1 frame\(s\)"):
        usable_frames([views[0][1], views[1][1][:2]], [CAMERA] * 2, NOMINAL, BuildConfig(),
                      said.append)


def test_problem_arrays_and_ids_per_frame(views) -> None:
    used = usable_frames([d for _, d in views], [CAMERA] * len(views), NOMINAL, BuildConfig(),
                         lambda _: None)
    p = problem_from(used, [CAMERA] * len(views), NOMINAL)
    n_obs = sum(len(dets) for _, _, dets in used)
    assert p.obs_px.shape == (n_obs, 4, 2) and p.intr.shape == (n_obs, 4)
    assert (p.n_frames, p.n_tags) == (len(used), len(NOMINAL))
    K = CAMERA.K
    np.testing.assert_array_equal(p.intr, np.tile([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], (n_obs, 1)))
    assert ids_per_frame(p, NOMINAL) == [[d.tag_id for d in dets] for _, _, dets in used]
    first = used[0][2][0]
    np.testing.assert_allclose(p.obs_px[0], first.corners_px, atol=1e-9)  # a pinhole: unchanged
    keep = p.obs_frame != 0
    sub = p.subset(keep)
    assert len(sub.obs_tag) == keep.sum() and sub.n_frames == p.n_frames


def test_coverage_problems_name_rare_tags_and_separate_groups() -> None:
    config = BuildConfig()
    ids = list(NOMINAL.ids)
    everything = [ids] * 3
    assert coverage_problems(NOMINAL, everything, config) == []
    rare = [ids] * 2 + [ids[1:]] * 2  # tag ids[0] in 2 frames only
    [problem] = coverage_problems(NOMINAL, rare, config)
    assert problem.startswith(f"tag(s) {ids[0]} (2) seen in too few frames") and "need 3" in problem
    half = len(ids) // 2
    split = [ids[:half]] * 3 + [ids[half:]] * 3  # never seen together
    [problem] = coverage_problems(NOMINAL, split, config)
    assert "2 groups never seen together" in problem
    # Frames with fewer tags than min_tags_per_frame count for nothing.
    thin = [ids] * 2 + [ids[:3]] * 5
    assert "seen in too few frames" in coverage_problems(NOMINAL, thin, config)[0]
