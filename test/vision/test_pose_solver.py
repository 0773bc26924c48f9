"""The joint pose's least-squares refinement (``pose._refine``, scipy's MINPACK Levenberg-Marquardt)
reaches the reprojection minimum from near and from far starts."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.cap_model import nominal_model
from ficap_ros.geometry.metrics import angle_deg
from ficap_ros.geometry.transform import CAM_FROM_FORWARD, Transform
from ficap_ros.vision.pose import _at, _make_obs, _refine

MODEL = nominal_model()
CAMERA = CameraModel.pinhole(1920, 1080, hfov_deg=60.0)


def _gauss_newton_step(obs, T: Transform) -> Transform:
    """One undamped Gauss-Newton step from ``T``: at the minimum it moves nothing."""
    res, J = _at(T, obs)
    dx = -np.linalg.solve(J.T @ J, J.T @ res)
    return Transform(Rotation.from_rotvec(dx[:3]) * T.rotation, T.translation_m + dx[3:])


def test_refine_reaches_the_least_squares_minimum() -> None:
    rng = np.random.default_rng(7)
    worst_deg = worst_mm = 0.0
    for k in range(30):
        ypr = rng.uniform(-1, 1, 3) * [50.0, 25.0, 10.0]
        T = Transform(CAM_FROM_FORWARD * Rotation.from_euler("ZYX", ypr, degrees=True),
                      [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.4, 0.7)])
        n = T.rotation.apply(MODEL.normals)
        c = T.apply(MODEL.centres_mm / 1000.0)
        facing = np.asarray(MODEL.ids)[np.sum(n * c, axis=1) < -0.2 * np.linalg.norm(c, axis=1)]
        corners = {int(i): CAMERA.project(T.apply(MODEL.corners_of(int(i)) / 1000.0))
                   + rng.normal(0.0, 0.3, (4, 2)) for i in facing}
        obs = _make_obs(corners, MODEL, CAMERA.K)
        # Starts as tracking gives them (a fraction of a degree off) and as a poor consensus might.
        off_deg, off_m = (0.2, 0.002) if k % 2 else (5.0, 0.03)
        start = Transform(Rotation.from_rotvec(rng.normal(0, 1, 3) * np.radians(off_deg) / np.sqrt(3)) * T.rotation,
                          T.translation_m + rng.normal(0, off_m, 3))
        ours, rms = _refine(obs, start)
        # At the minimum the gradient vanishes: a further Gauss-Newton step stays put.
        ref = _gauss_newton_step(obs, ours)
        worst_deg = max(worst_deg, float(angle_deg(ours.rotation, ref.rotation)))
        worst_mm = max(worst_mm, 1000.0 * float(np.abs(ours.translation_m - ref.translation_m).max()))
        assert 0.3 < rms < 0.55  # 0.3 px per coordinate: 0.42 px per corner
        assert float(angle_deg(ours.rotation, T.rotation)) < 0.2  # the minimum near the truth, not the start
    assert worst_deg < 1e-6 and worst_mm < 1e-6, (worst_deg, worst_mm)


@pytest.mark.parametrize("direct", [True, False])
def test_refine_is_least_squares_lm_bit_for_bit(direct: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """``_refine`` calls MINPACK's lmder as ``least_squares(method="lm")`` does (without that
    wrapper's per-call cost): the same pose and rms to the last bit, from near and far starts, so
    labels do not move; a scipy upgrade that makes the two differ shows here. Without the private
    lmder (another scipy) it goes through least_squares itself: the same answers."""
    from scipy.optimize import least_squares

    from ficap_ros.vision import pose
    from ficap_ros.vision.pose import _residuals_and_jacobian

    if direct:  # the pinned scipy has it: the fast path is the one tested
        assert pose._lmder is not None and pose._direct_lmder_works()
    monkeypatch.setattr(pose, "_DIRECT_LMDER", direct)

    rng = np.random.default_rng(11)
    for k in range(12):
        T = Transform(CAM_FROM_FORWARD * Rotation.from_euler("ZYX", rng.uniform(-1, 1, 3) * [40.0, 20.0, 10.0],
                                                             degrees=True),
                      [rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.4, 0.7)])
        corners = {int(i): CAMERA.project(T.apply(MODEL.corners_of(int(i)) / 1000.0)) + rng.normal(0.0, 0.3, (4, 2))
                   for i in MODEL.ids[:6 + k]}
        obs = _make_obs(corners, MODEL, CAMERA.K)
        # Near starts (tracking) and far ones, where LM's step bound and damping shape the path.
        off_deg, off_m = (0.5, 0.003) if k % 2 else (10.0, 0.05)
        start = Transform(Rotation.from_rotvec(rng.normal(0, 1, 3) * np.radians(off_deg)) * T.rotation,
                          T.translation_m + rng.normal(0, off_m, 3))
        ours, rms = _refine(obs, start)
        R0, x0 = start.rotation_matrix, np.concatenate([np.zeros(3), start.translation_m])
        sol = least_squares(lambda x: _residuals_and_jacobian(x, R0, obs.K, obs.model_m, obs.image_px)[0], x0,
                            jac=lambda x: _residuals_and_jacobian(x, R0, obs.K, obs.model_m, obs.image_px)[1],
                            method="lm", xtol=1e-10, ftol=1e-10, max_nfev=50)
        ref = Rotation.from_rotvec(sol.x[:3]) * start.rotation
        assert np.array_equal(ours.rotation.as_quat(), ref.as_quat())
        assert np.array_equal(ours.translation_m, sol.x[3:])
        assert rms == float(np.sqrt(np.mean(sol.fun**2) * 2.0))
