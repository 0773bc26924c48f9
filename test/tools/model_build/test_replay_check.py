"""ficap_ros.tools.model_build.replay_check: the recording posed with the nominal and the built model,
a grown cap refused, a worse fit warned of; the size hand assembly allows and the distance limit."""

from __future__ import annotations

import numpy as np
import pytest
from cap_views import CAMERA

from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.tools.model_build import replay_check, size_ratio


def test_replay_check_compares_with_the_nominal(built) -> None:
    truth, frames, result = built
    dets = [d for _, d in frames]
    check = replay_check(dets, CAMERA, result.model)
    assert check.ok and check.frames == 40
    assert check.rms_px_built < check.rms_px_nominal
    assert abs(check.depth_change) < 5e-4
    assert "nominal" in check.table() and check.to_dict()["problems"] == []
    # A cap grown by 1 % around its centre would place the cap ~5 mm too far: refused.
    c = result.model.corners_mm
    grown = CapModel(result.model.ids, c.mean(axis=(0, 1)) + 1.01 * (c - c.mean(axis=(0, 1))))
    assert size_ratio(grown.corners_mm, c) == pytest.approx(1.01)
    bad = replay_check(dets, CAMERA, grown)
    assert bad.depth_change == pytest.approx(0.01, abs=0.002) and bad.translation_change_mm > 3.0
    assert bad.problems
    # A model with every plate moved ~1.5 mm more fits the frames worse than the nominal: a warning.
    moved = c + np.random.default_rng(3).normal(0.0, 1.5 / np.sqrt(3.0), (len(c), 1, 3))
    worse = replay_check(dets, CAMERA, CapModel(result.model.ids, moved))
    assert worse.warnings and "fits the recording worse" in worse.warnings[0]
    assert worse.rms_px_built > worse.rms_px_nominal


def test_the_size_hand_assembly_allows_and_the_distance_limit(built) -> None:
    import dataclasses

    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.tools.model_build import (
        BuildConfig,
        assembly_size_sigma,
        depth_change_limit,
    )
    from ficap_ros.tools.model_build.geometry import rms_radius

    nominal = nominal_model()
    sigma = assembly_size_sigma(nominal, BuildConfig())
    assert sigma == pytest.approx(1.0 / (np.sqrt(23) * rms_radius(nominal.centres_mm)), rel=1e-12)
    assert assembly_size_sigma(nominal, BuildConfig(assembly_sigma_mm=0.5)) == pytest.approx(sigma / 2)
    _, _, result = built
    config = BuildConfig()
    side = dataclasses.replace(result, size_source="tag side")
    assert depth_change_limit(side, config) == pytest.approx(max(0.003, 3 * sigma))
    assert depth_change_limit(side, BuildConfig(size="fixed")) == 0.003
    assert depth_change_limit(dataclasses.replace(result, size_source="nominal layout"),
                              config) == 0.003
    assert depth_change_limit(side, BuildConfig(max_depth_change=0.5)) == 0.5


def test_frames_and_cameras_must_pair_and_unposed_frames_are_a_problem(built) -> None:
    from ficap_ros.errors import ConfigError

    _, frames, result = built
    dets = [d for _, d in frames[:3]]
    with pytest.raises(ConfigError, match="3 frames but 2 cameras"):
        replay_check(dets, [CAMERA, CAMERA], result.model)
    check = replay_check([[] for _ in dets], CAMERA, result.model)  # no tags: no pose
    assert check.frames == 0 and not check.ok
    assert check.problems == ("no frame could be posed by both models",)
    assert np.isnan(check.depth_change) and check.to_dict()["warnings"] == []
