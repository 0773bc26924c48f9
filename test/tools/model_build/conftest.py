"""Fixtures of the as-built model's tests: one build from 40 frames of a perturbed cap."""

from __future__ import annotations

import pytest
from cap_views import CAMERA, observe, perturbed_model

from ficap_ros.tools.model_build import build_model


@pytest.fixture(scope="session")
def built():
    """(truth, its 40 observed frames, the build from them): a cap with every plate off by 0.5 mm
    rms and turned 1 deg, seen with 0.15 px of corner noise."""
    truth = perturbed_model(seed=1)
    frames = observe(truth, count=40, seed=2)
    result = build_model([dets for _, dets in frames], CAMERA)
    return truth, frames, result
