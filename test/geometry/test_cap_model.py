"""The nominal cap against every self-check of cap-spec.md, and model files round-tripping."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ficap_ros.errors import ModelError
from ficap_ros.geometry.cap_model import (
    SPHERE_RADIUS_MM,
    TAG_SIDE_MM,
    CapModel,
    load_model,
    nominal_model,
)

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def model() -> CapModel:
    return nominal_model()


def test_counts(model: CapModel) -> None:
    assert len(model) == 23
    assert model.ids == tuple(range(23))
    assert model.corners_mm.reshape(-1, 3).shape == (92, 3)


def test_sphere_radius() -> None:
    assert SPHERE_RADIUS_MM == pytest.approx(92.114, abs=5e-4)


def test_minimum_angle_between_normals(model: CapModel) -> None:
    n = model.normals
    angles = np.degrees(np.arccos(np.clip(n @ n.T, -1.0, 1.0)))
    np.fill_diagonal(angles, np.inf)
    assert angles.min() == pytest.approx(24.5, abs=1e-6)


def test_corner_distance_from_origin(model: CapModel) -> None:
    s = TAG_SIDE_MM / 2
    d = np.linalg.norm(model.corners_mm, axis=2)
    np.testing.assert_allclose(d, math.sqrt(SPHERE_RADIUS_MM**2 + 2 * s**2), atol=1e-9)


def test_centre_tag_normal(model: CapModel) -> None:
    np.testing.assert_allclose(model.normals[model.index_of(11)], [-1.0, 0.0, 0.0], atol=1e-12)


def test_squares_are_32mm_and_tangent(model: CapModel) -> None:
    c = model.corners_mm
    sides = np.linalg.norm(c - np.roll(c, 1, axis=1), axis=2)
    np.testing.assert_allclose(sides, TAG_SIDE_MM, atol=1e-9)
    # Face centre on the sphere along its own normal.
    np.testing.assert_allclose(model.centres_mm, SPHERE_RADIUS_MM * model.normals, atol=1e-9)


def test_corner_order_seen_from_outside(model: CapModel) -> None:
    """TL->TR points to the wearer's right for the centre tag (camera right), TL->BL down."""
    c = model.corners_of(11)
    np.testing.assert_allclose((c[1] - c[0]) / TAG_SIDE_MM, [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose((c[3] - c[0]) / TAG_SIDE_MM, [0, 0, -1], atol=1e-12)


def test_rows_and_id_order(model: CapModel) -> None:
    """Ids run row by row from the top, left to right as seen from behind (decreasing y)."""
    el = np.degrees(np.arcsin(model.normals[:, 2]))
    rows = [(0, 3, 49.0), (3, 8, 24.5), (8, 15, 0.0), (15, 20, -24.5), (20, 23, -49.0)]
    for start, stop, elevation in rows:
        np.testing.assert_allclose(el[start:stop], elevation, atol=1e-9)
        y = model.centres_mm[start:stop, 1]
        assert np.all(np.diff(y) < 0)


def test_no_tag_covered_by_a_neighbouring_face(model: CapModel) -> None:
    """No tag corner lies inside another face's square when seen along that face's normal,
    in front of its plane (a neighbouring face would cover it)."""
    faces = model.face_corners_mm()
    normals = model.normals
    for j in range(len(model)):
        centre = faces[j].mean(axis=0)
        u = faces[j][1] - faces[j][0]
        v = faces[j][3] - faces[j][0]
        u_hat, v_hat = u / np.linalg.norm(u), v / np.linalg.norm(v)
        for i in range(len(model)):
            if i == j:
                continue
            for p in model.corners_mm[i]:
                rel = p - centre
                height = rel @ normals[j]
                inside = abs(rel @ u_hat) < 20.0 - 1e-6 and abs(rel @ v_hat) < 20.0 - 1e-6
                assert not (inside and height < 0.0), (i, j)


def test_yaml_round_trip(tmp_path: Path, model: CapModel) -> None:
    path = tmp_path / "cap.yaml"
    model.save(path)
    assert load_model(path) == model


def test_config_nominal_yaml_is_generated_from_code(model: CapModel) -> None:
    shipped = load_model(ROOT / "config" / "cap_nominal.yaml")
    assert shipped.ids == model.ids
    np.testing.assert_allclose(shipped.corners_mm, model.corners_mm, atol=1e-9)


def test_duplicate_ids_rejected(model: CapModel) -> None:
    with pytest.raises(ModelError, match="duplicate tag id 3"):
        CapModel((1, 3, 3), model.corners_mm[:3])


@pytest.mark.parametrize(
    "text, message",
    [
        ("tags: 5", "expected a mapping"),
        ("tags: [{id: 1}]", "needs 'id' and 'corners_mm'"),
        ("tags: [{id: 1, corners_mm: [[0, 0, 0]]}]", "4 corners of 3 numbers"),
        ("tags: [{id: 1, corners_mm: [[0, 0, true], [1, 0, 0], [1, 1, 0], [0, 1, 0]]}]",
         "4 corners of 3 numbers"),
        ("tags: [{id: 587, corners_mm: [[0, 0, 0], [32, 0, 0], [32, 32, 0], [0, 32, 0]]}]",
         r"not a tag36h11 id \(0 to 586\)"),
        ("tags: [{id: 1, corners_mm: [[0, 0, 0], [1.0e+308, 0, 0], [1, 1, 0], [0, 1, 0]]}]",
         "from the cap origin"),
        ("tags: [{id: 1, corners_mm: [[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0]]}]",
         "span a square"),
        ("a: &x [1, 2]\nb: *x\n", "aliases"),
        ("units: m\ntags: []", "units must be 'mm'"),
        ("tags: [", "not valid YAML"),
    ],
)
def test_bad_model_files(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ModelError, match=message):
        load_model(path)


def test_cli_model_json(model: CapModel) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "ficap_ros.cli", "model", "--json"],
        capture_output=True, text=True, check=True,
    ).stdout
    data = json.loads(out)
    assert data["frame"] == "cap" and data["units"] == "mm"
    assert [t["id"] for t in data["tags"]] == list(range(23))
    np.testing.assert_allclose(
        np.array([t["corners_mm"] for t in data["tags"]]), model.corners_mm, atol=1e-9
    )


def test_cli_bad_model_exits_one_line(tmp_path: Path) -> None:
    path = tmp_path / "dup.yaml"
    m = nominal_model()
    d = m.to_dict()
    d["tags"][1]["id"] = 0
    path.write_text(json.dumps(d))
    proc = subprocess.run(
        [sys.executable, "-m", "ficap_ros.cli", "model", "--model", str(path)],
        capture_output=True, text=True,
    )
    assert proc.returncode == 1
    assert proc.stderr.strip().count("\n") == 0
    assert "duplicate tag id 0" in proc.stderr
