"""ficap_ros.tools.model_build.adjustment: zero residuals at the truth, the projection is the
camera's, the sparse grouped Jacobian equals a dense numerical one, the solve returns to the truth
from a perturbed start, and covariances turn with the points."""

from __future__ import annotations

import numpy as np
import pytest
from cap_views import CAMERA, observe, perturbed_model, rigid_rms_mm

from ficap_ros.geometry.cap_model import CapModel, nominal_model
from ficap_ros.tools.model_build import BuildConfig, edge_shift_px
from ficap_ros.tools.model_build.adjustment import (
    initial_values,
    jacobian,
    n_params,
    observation_rms_px,
    project,
    residuals,
    rotate_covariance,
    solve,
    unpack,
)
from ficap_ros.tools.model_build.geometry import corners_from_params
from ficap_ros.tools.model_build.observations import problem_from

NOMINAL = nominal_model()


def _problem(model, count: int, seed: int):
    """The observations of ``count`` exact views of ``model`` with their true camera poses."""
    frames = observe(model, count=count, seed=seed, noise_px=0.0)
    used = [(i, T, dets) for i, (T, dets) in enumerate(frames)]
    return problem_from(used, [CAMERA] * count, NOMINAL), [T for T, _ in frames]


@pytest.mark.parametrize("config", [BuildConfig(), BuildConfig(fit_edge_offset=False,
                                                               anchor_size=False)])
def test_residuals_vanish_at_the_truth(config: BuildConfig) -> None:
    p, poses = _problem(NOMINAL, 4, 41)
    x0, priors = initial_values(NOMINAL, poses, config)
    assert x0.size == n_params(p, config) == 6 * (len(NOMINAL) + 4) + int(config.fit_edge_offset)
    r = residuals(x0, p, priors, config)
    assert r.size == 8 * len(p.obs_tag) + 6 * len(NOMINAL) + int(config.anchor_size)
    assert np.abs(r).max() < 1e-8
    assert np.abs(observation_rms_px(x0, p, priors, config)).max() < 1e-8
    tags, offset, frames = unpack(x0, p, config)
    assert tags.shape == (len(NOMINAL), 6) and frames.shape == (4, 6) and offset == 0.0
    np.testing.assert_allclose(frames[:, 3:], [1000.0 * T.translation_m for T in poses])


def test_projection_is_the_cameras_and_the_offset_moves_the_edges() -> None:
    p, poses = _problem(NOMINAL, 3, 43)
    config = BuildConfig()
    x0, priors = initial_values(NOMINAL, poses, config)
    tags, _, frames = unpack(x0, p, config)
    got = project(tags, frames, p)
    for k, (f, t) in enumerate(zip(p.obs_frame, p.obs_tag)):
        want = CAMERA.project(poses[f].apply(NOMINAL.corners_mm[t] / 1000.0))
        np.testing.assert_allclose(got[k], want, atol=1e-9)
    x = x0.copy()
    x[6 * len(NOMINAL)] = 0.4  # the edge offset
    corner_rows = residuals(x, p, priors, config)[: 8 * len(p.obs_tag)].reshape(-1, 4, 2)
    np.testing.assert_allclose(corner_rows, edge_shift_px(got, 0.4) - got, atol=1e-9)


def test_sparse_jacobian_equals_a_dense_numerical_one() -> None:
    truth = perturbed_model(seed=5)
    p, poses = _problem(truth, 3, 45)
    config = BuildConfig()
    x0, priors = initial_values(NOMINAL, poses, config)
    x = x0 + np.random.default_rng(1).normal(0.0, 1e-3, x0.size)
    J = jacobian(x, p, priors, config).toarray()
    dense = np.empty_like(J)
    for k in range(x.size):
        h = 1e-6 * max(1.0, abs(x[k]))
        hi, lo = x.copy(), x.copy()
        hi[k] += h
        lo[k] -= h
        dense[:, k] = (residuals(hi, p, priors, config) - residuals(lo, p, priors, config)) / (2 * h)
    scale = np.abs(dense).max()
    np.testing.assert_allclose(J, dense, atol=2e-5 * scale)


def test_solve_returns_to_the_truth_from_a_perturbed_start() -> None:
    truth = perturbed_model(seed=6)
    p, poses = _problem(truth, 12, 46)
    config = BuildConfig(fit_edge_offset=False, anchor_size=False)
    x0, priors = initial_values(NOMINAL, poses, config)
    start = observation_rms_px(x0, p, priors, config)
    assert np.sqrt(np.mean(start ** 2)) > 0.3  # the nominal cap does not fit these views
    solution = solve(p, x0, priors, config)
    assert solution.success
    rms = observation_rms_px(solution.x, p, priors, config)
    assert np.sqrt(np.mean(rms ** 2)) < 0.02  # only the priors pull the plates off their places
    tags, _, _ = unpack(solution.x, p, config)
    built = CapModel(NOMINAL.ids, corners_from_params(tags[:, :3], tags[:, 3:]))
    assert rigid_rms_mm(built, truth) < 0.02


def test_rotate_covariance_turns_points_and_keeps_isotropy() -> None:
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xyz", [20.0, -40.0, 65.0], degrees=True).as_matrix()
    iso = np.einsum("ij,ab->iajb", np.eye(2), np.eye(3) * 0.3)
    np.testing.assert_allclose(rotate_covariance(iso, R), iso, atol=1e-15)
    aniso = np.zeros((1, 3, 1, 3))
    aniso[0, :, 0, :] = np.diag([1.0, 0.0, 0.0])  # variance along x only
    turned = rotate_covariance(aniso, R)[0, :, 0, :]
    np.testing.assert_allclose(turned, np.outer(R[:, 0], R[:, 0]), atol=1e-15)
