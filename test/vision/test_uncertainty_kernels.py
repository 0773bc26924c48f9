"""The pose uncertainty's compiled kernel against the vectorised numpy formulas it replaces
(test/helpers/uncertainty_reference.py): every unit covariance, every sigma and dof the residuals
show, and the fit's map equal to rounding (1e-9 of each quantity's scale) for random cap
poses, tag subsets, tag weights, cameras with skew and a moving fit's prior (twelve unknowns)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from uncertainty_reference import reference_terms

from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.vision.reprojection import TagObservations, residuals_and_jacobian
from ficap_ros.vision.uncertainty import _SEEN_NAMES, _TERM_NAMES, _model_geometry
from ficap_ros.vision.uncertainty_kernels import propagated_terms

MODEL = nominal_model()


def _case(seed: int, tags: int, weighted: bool, prior: bool):  # noqa: ANN202
    rng = np.random.default_rng(seed)
    T = Transform(CAM_FROM_FORWARD * Rotation.from_euler("ZYX", rng.uniform(-1, 1, 3) * [40.0, 20.0, 10.0],
                                                         degrees=True),
                  [rng.normal(0.0, 0.03), rng.normal(0.0, 0.03), rng.uniform(0.4, 0.9)])
    K = np.array([[rng.uniform(500, 1500), rng.normal(0.0, 1.0), rng.uniform(300, 900)],
                  [0.0, rng.uniform(500, 1500), rng.uniform(200, 500)], [0.0, 0.0, 1.0]])
    ids = sorted(rng.choice(MODEL.ids, size=tags, replace=False).tolist())
    model_m = np.stack([MODEL.corners_of(int(i)) for i in ids]) / 1000.0
    cam = model_m.reshape(-1, 3) @ T.rotation_matrix.T + T.translation_m
    q = cam @ K.T
    image = (q[:, :2] / q[:, 2:3] + rng.normal(0.0, 0.3, (len(cam), 2))).reshape(-1, 4, 2)
    obs = TagObservations(tuple(ids), image, model_m, K)
    res, J = residuals_and_jacobian(T, obs)
    info = None
    if prior:  # a moving fit: six velocity columns and a prior on them
        J = np.concatenate([J, J * rng.uniform(-0.02, 0.02, (len(J), 1))], axis=1)
        info = np.diag(np.r_[np.zeros(6), rng.uniform(1e3, 1e5, 6)])
    rel = rng.uniform(0.5, 2.0, tags) if weighted else np.ones(tags)
    return obs, T, res, J, rel, info


def _kernel(obs: TagObservations, T: Transform, res: np.ndarray, J: np.ndarray, rel: np.ndarray,
            info: np.ndarray | None):  # noqa: ANN202
    centres, normal, cross = _model_geometry(obs)
    k = J.shape[1]
    return propagated_terms(res, np.ascontiguousarray(J), np.repeat(1.0 / rel**2, 8),
                            np.zeros((k, k)) if info is None else info, obs.image_px.reshape(-1, 2),
                            obs.model_m.reshape(-1, 3), np.array(T.rotation_matrix),
                            np.array(T.translation_m), obs.K, rel, cross, centres, normal)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(2, 23), st.booleans(), st.booleans())
def test_the_kernel_equals_the_numpy_formulas(seed: int, tags: int, weighted: bool, prior: bool) -> None:
    obs, T, res, J, rel, info = _case(seed, tags, weighted, prior)
    ref_terms, ref_seen, ref_A = reference_terms(obs, T, res, J, rel, info)
    terms, seen, A_ros = _kernel(obs, T, res, J, rel, info)
    np.testing.assert_allclose(A_ros, ref_A, rtol=0, atol=1e-9 * np.abs(ref_A).max())
    for name, term in zip(_TERM_NAMES, terms):
        # Relative to each block's largest variance (translation m^2, rotation rad^2): a pose
        # direction a source barely moves is a sum that cancels, its rounding relatively large.
        d = np.diag(ref_terms[name])
        block = np.repeat([d[:3].max(), d[3:].max()], 3)
        scale = np.sqrt(np.outer(block, block)) + 1e-300
        assert np.all(np.abs(term - ref_terms[name]) <= 1e-9 * scale), name
    for name, value in zip(_SEEN_NAMES, seen):
        assert value == pytest.approx(ref_seen[name], rel=1e-9, abs=1e-12), name
    assert seen[-1] == pytest.approx(ref_seen["mean_scale"], rel=1e-9, abs=1e-12)


def test_a_singular_fit_gives_infinite_terms() -> None:
    """A Jacobian of rank < 6 (a pose column zero): the map is infinite (the covariance becomes
    "unknown" downstream), as where numpy's inverse refuses the normal matrix."""
    obs, T, res, J, rel, _ = _case(3, 2, False, False)
    J[:, 5] = 0.0
    terms, _seen, A_ros = _kernel(obs, T, res, J, rel, None)
    assert not np.all(np.isfinite(A_ros))
    assert not np.all(np.isfinite(terms[_TERM_NAMES.index("noise")]))


@settings(max_examples=40, deadline=None)
@given(turn_deg=st.floats(-180.0, 180.0), squash=st.floats(0.2, 1.0), shift=st.floats(-500.0, 500.0))
def test_tag_basis_columns_point_along_their_patterns(turn_deg: float, squash: float, shift: float) -> None:
    """Every tag's scale column is the normalised radial pattern itself, never its negative, at
    any turn, foreshortening and place in the image: a radial offset shared by the tags gives
    every tag a scale coefficient of one sign, so their mean measures it (a QR's own column
    signs follow the data)."""
    from ficap_ros.vision.uncertainty_kernels import _tag_basis

    a = np.deg2rad(turn_deg)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    square = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * [20.0, 20.0 * squash]
    corners = square @ rot.T + [640.0 + shift, 360.0 - 0.5 * shift]
    B = _tag_basis(corners)
    radial = (corners - corners.mean(axis=0)).ravel()
    np.testing.assert_allclose(B[:, 2], radial / np.linalg.norm(radial), atol=1e-12)
    np.testing.assert_allclose(B[:, :2], np.tile(np.eye(2), (4, 1)) / 2.0, atol=1e-12)
    np.testing.assert_allclose(B.T @ B, np.eye(8), atol=1e-12)
