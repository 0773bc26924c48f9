"""ficap_ros.tools.model_build.report: the build result as a model file, a table and plain data."""

from __future__ import annotations

import numpy as np
import pytest

from ficap_ros.geometry.cap_model import load_model, nominal_model


def test_result_is_a_normal_model_file(built, tmp_path) -> None:
    _, _, result = built
    path = tmp_path / "cap_asbuilt.yaml"
    result.model.save(path)
    loaded = load_model(path)
    assert loaded.ids == nominal_model().ids
    np.testing.assert_allclose(loaded.corners_mm, result.model.corners_mm, atol=1e-9)


def test_table_and_plain_data_say_the_same(built) -> None:
    import json

    _, _, result = built
    data = json.loads(json.dumps(result.to_dict()))  # plain JSON: no numpy, no NaN
    assert [t["id"] for t in data["tags"]] == list(result.model.ids)
    for tag, d in zip(data["tags"], result.deviations):
        np.testing.assert_allclose(tag["offset_mm"], d.offset_mm)
        assert tag["offset_norm_mm"] == pytest.approx(np.linalg.norm(d.offset_mm))
        assert tag["frames"] == d.frames and tag["problem"] == d.problem
    assert data["trusted"] is True and data["problems"] == [] and data["converged"] is True
    assert data["frames_used"] == result.frames_used == 40 and data["frames_given"] == 40
    assert data["corner_rms_mm"] == pytest.approx(result.corner_rms_mm)
    # The side a side-only scale would read: 32 mm grown by twice the offset at the median side.
    assert result.effective_side_mm == pytest.approx(
        32.0 * (1.0 + 2.0 * result.edge_offset_px / result.median_side_px))
    lines = result.table().splitlines()
    assert len(lines) == 1 + len(result.deviations) + 4
    assert all(line.split()[0] == str(d.tag_id) and line.endswith("ok")
               for line, d in zip(lines[1:], result.deviations))
    assert f"frames used {result.frames_used}/40" in lines[-4]
    assert lines[-1].startswith("solver converged")


def test_a_result_with_problems_is_not_trusted(built) -> None:
    import dataclasses

    _, _, result = built
    doubtful = dataclasses.replace(result, problems=("tag 3 seen in 1 frame(s)",),
                                   converged=False, size_ratio_images=float("nan"))
    assert not doubtful.trusted
    assert doubtful.table().splitlines()[-1] == "PROBLEM: tag 3 seen in 1 frame(s)"
    assert "NOT CONVERGED" in doubtful.table()
    data = doubtful.to_dict()
    assert data["trusted"] is False and data["size_ratio_images"] is None


def test_tag_deviation_holds_a_frozen_offset() -> None:
    from ficap_ros.tools.model_build import TagDeviation

    d = TagDeviation(4, [3.0, 4.0, 0.0], 0.1, 1.0, 0.5, 0.1, 0.3, 0.05, 9, 10.0, 50.0, 60.0, 0.2)
    assert d.offset_norm_mm == 5.0 and d.offset_mm.dtype == np.float64
    assert not d.offset_mm.flags.writeable and d.problem == ""
    with pytest.raises(ValueError):
        TagDeviation(4, [3.0, 4.0], 0.1, 1.0, 0.5, 0.1, 0.3, 0.05, 9, 10.0, 50.0, 60.0, 0.2)
