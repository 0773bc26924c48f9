"""ficap_ros.tools.model_build.config: BuildConfig's defaults and its validation, one field at a
time; CoverageError is a model error (one line, exit 1 from the CLI)."""

from __future__ import annotations

import math

import pytest

from ficap_ros.errors import ConfigError, FicapError, ModelError
from ficap_ros.tools.model_build import BuildConfig, CoverageError


def test_defaults() -> None:
    c = BuildConfig()
    assert (c.min_tags_per_frame, c.min_frames_per_tag, c.max_frames) == (4, 3, 400)
    assert (c.loss, c.f_scale_px, c.outlier_px, c.max_nfev) == ("soft_l1", 1.0, 3.0, 100)
    assert (c.assembly_sigma_mm, c.assembly_sigma_deg) == (1.0, 2.0)
    assert c.fit_edge_offset and c.anchor_size and c.size == "auto" and c.edge_offset_px == 0.0
    assert (c.max_corner_sigma_mm, c.min_view_spread_deg, c.max_depth_change) == (0.25, 0.0, 0.003)


@pytest.mark.parametrize("field, bad, good", [
    ("min_tags_per_frame", 1, 2), ("min_frames_per_tag", 0, 1), ("max_frames", 1, 2),
    ("max_nfev", 0, 1), ("size", "images", "fixed"), ("loss", "l2", "cauchy"),
    ("f_scale_px", 0.0, 0.1), ("assembly_sigma_mm", -1.0, 0.2), ("assembly_sigma_deg", 0.0, 0.5),
    ("outlier_px", 0.0, 1.0), ("max_corner_sigma_mm", -0.1, 1.0), ("max_depth_change", 0.0, 0.01),
    ("edge_offset_px", 5.5, -5.0), ("edge_offset_px", math.nan, 0.3),
    ("min_view_spread_deg", 180.0, 179.0), ("min_view_spread_deg", -1.0, 0.0),
])
def test_each_field_is_checked_by_itself(field: str, bad: object, good: object) -> None:
    with pytest.raises(ConfigError) as info:
        BuildConfig(**{field: bad})
    assert "\n" not in str(info.value)
    assert field in str(info.value) or field == "loss" and "loss" in str(info.value)
    assert getattr(BuildConfig(**{field: good}), field) == good  # the edge of the range is taken


def test_coverage_error_is_a_model_error() -> None:
    assert issubclass(CoverageError, ModelError) and issubclass(CoverageError, FicapError)
