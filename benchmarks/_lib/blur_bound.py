"""A Cramer-Rao bound of the cap's rotation from a frame's pixels, blurred or not, global or rolling shutter.

Per tag, the Fisher information of its mid-exposure homography is that of the moving photometric
model (``photometric_kernels.coverage_moving`` / ``model_rows_moving``: the pattern moving over
the exposure along the truth's path, averaged in linear light, through the tone curve) at the
truth's corners, with the levels, lens blur and tone exponent the fit finds there and the pixel
noise its robust residual sd; the levels, blur and tone are nuisance parameters (marginalised).
The tags' corner covariances then bound the pose (the static pose's Jacobian), and the bound's
rotation error is drawn from its covariance: the median of such draws over a set of frames is what
an efficient estimator's median would be.

Through a rolling shutter each corner is seen at its row's time (``CameraTiming.row_time_s``): its
tag's pixels are modelled along the truth's path around that time, and the pose at the stamp is
bounded through the corners' positions at their times with the cap's motion over the readout known
(the truth's, the quadratic through the poses a frame before and after): the bound of an estimator
that knows the velocity and acceleration exactly, which a two-sided estimate from the neighbouring
frames approaches.
"""

from __future__ import annotations

import numpy as np

from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.geometry.tag36h11 import (
    homography_corners,
    stacked_tag_cells,
    tag_homographies,
)
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision import photometric, photometric_kernels
from ficap_ros.vision.reprojection import residuals_and_jacobian_rt

__all__ = ["frame_rotation_draws"]

_SD_PX = float(np.sqrt(photometric.PSF_SIGMA_PX ** 2 + 1.0 / 12.0))


def _tag_corner_covariance(gray: np.ndarray, corners_px: np.ndarray, motion_px: np.ndarray,
                           bend_px: np.ndarray, tag_id: int) -> np.ndarray | None:
    """(8, 8) the bound's covariance of one tag's corners (x0, y0, ... x3, y3), px^2; None where
    the tag's pixels do not fit (too few, or a misfit)."""
    hom = tag_homographies(corners_px[None])
    hom = hom / hom[:, 2:3, 2:3]
    table = photometric._black_tables(stacked_tag_cells((int(tag_id),)))
    reach = 1.0 + 0.5 * np.linalg.norm(motion_px, axis=1).max()
    _, xi, yi = photometric._select_pixels(gray.shape[:2], hom, table, _SD_PX, np.array([reach]), 1500)
    if len(xi) < 40:
        return None
    warps, instants = photometric.motion_warps(corners_px[None], motion_px[None], _SD_PX, bend_px[None])
    obs, x, y = gray[yi, xi].astype(np.float64), xi.astype(np.float64), yi.astype(np.float64)
    h = hom.reshape(1, 9)[:, :8].copy()
    theta = np.zeros((1, 8))
    ok, misfit, _ = photometric_kernels.fit_steps_moving(
        obs, x, y, np.zeros(1, np.int64), np.array([len(obs)], np.int64), h, theta, table, warps, instants,
        _SD_PX, True, 6, 40, 5, 1e-3, 0.01)
    if not ok[0] or misfit[0] > 0.3:
        return None
    h0 = hom.reshape(9)[:8].copy()  # the truth's homography, the fitted nuisance parameters
    n, k = len(obs), int(instants[0])
    mean, jac, r = np.empty((n, 12)), np.empty((n, 16)), np.empty(n)
    bu, bv = np.empty((n, k), np.int64), np.empty((n, k), np.int64)
    photometric_kernels.coverage_moving(x, y, h0, _SD_PX * np.exp(theta[0, 6]), table[0], warps[0, :k], True,
                                        bu, bv, mean, np.empty((2, 3, 4)))
    photometric_kernels.model_rows_moving(obs, theta[0], mean, True, jac, r)
    sigma = max(1.4826 * float(np.median(np.abs(r))), 0.5)
    cov_h = np.linalg.inv(jac.T @ jac / sigma ** 2)[:8, :8]
    G = np.empty((8, 8))
    for j in range(8):
        step = np.zeros(8)
        step[j] = 1e-7 * max(abs(h0[j]), 1e-3)
        G[:, j] = (homography_corners((h0 + step)[None]) - homography_corners((h0 - step)[None])).reshape(8) / (2 * step[j])
    return G @ cov_h @ G.T


def _path(truths: tuple[Transform, Transform, Transform], dt_s: float):  # noqa: ANN202
    """The cap's motion relative to its pose at the stamp, ``delta(t)`` (the quadratic through
    the poses a frame before, at and after the stamp; rotations as vectors at the stamp's)."""
    T0 = truths[1]
    r = [(T * T0.inv()).rvec for T in (truths[0], truths[2])]
    x = [T.translation_m - T0.translation_m for T in (truths[0], truths[2])]

    def delta(t: float) -> Transform:
        rot = (r[1] - r[0]) / (2 * dt_s) * t + (r[1] + r[0]) / (2 * dt_s**2) * t * t
        moved = (x[1] - x[0]) / (2 * dt_s) * t + (x[1] + x[0]) / (2 * dt_s**2) * t * t
        # A rotation about the cap origin, then the origin moved: applied to T0 it gives the path.
        turn = Transform.from_rvec_tvec(rot, np.zeros(3))
        return Transform.from_rvec_tvec(np.zeros(3), moved + T0.translation_m - turn.apply(T0.translation_m[None])[0]) * turn

    return delta


def _rolling_jacobian(camera: CameraModel, corners_m: np.ndarray, T0: Transform, delta,  # noqa: ANN001
                      times_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(corners at their times (4, 2) px, (8, 6) their derivative by a left perturbation of the
    pose at the stamp, columns (d_theta, d_t)), the motion ``delta`` known."""
    def corners(T: Transform) -> np.ndarray:
        return np.array([camera.project((delta(t) * T).apply(c[None]))[0] for t, c in zip(times_s, corners_m)])

    at = corners(T0)
    J = np.empty((8, 6))
    for j in range(6):
        dx = np.zeros(6)
        dx[j] = 1e-6
        plus = corners(T0.turned(dx[:3], T0.translation_m + dx[3:]))
        minus = corners(T0.turned(-dx[:3], T0.translation_m - dx[3:]))
        J[:, j] = (plus - minus).reshape(8) / 2e-6
    return at, J


def frame_rotation_draws(gray: np.ndarray, camera: CameraModel, model: CapModel, ids: list[int],
                         truths: tuple[Transform, Transform, Transform], dt_s: float, exposure_s: float,
                         rng: np.random.Generator, draws: int = 200,
                         timing: CameraTiming | None = None) -> np.ndarray:
    """Rotation errors, deg, drawn from the bound of one frame's pose from its tags ``ids``.

    Args:
        gray: the frame, uint8 grey.
        camera, model: its camera and the cap model.
        ids: the tags the bound uses (those the estimator used).
        truths: the poses one frame before, at, and one frame after the frame's stamp.
        dt_s: the time between consecutive frames, s.
        exposure_s: the exposure, s.
        rng, draws: the draws' generator and count.
        timing: the camera's timing; a rolling shutter's corners are bounded at their row times
            (module docstring). None: a global shutter.

    Returns:
        (draws,) geodesic rotation errors, deg (empty where fewer than 3 tags are bounded).
    """
    info = np.zeros((6, 6))
    tags = 0
    rolling = timing is not None and timing.rolling
    delta = _path(truths, dt_s) if rolling else None
    for tag_id in ids:
        corners_m = 1e-3 * model.corners_of(tag_id)
        p = [camera.project(T.apply(corners_m)) for T in truths]
        velocity, accel = (p[2] - p[0]) / (2 * dt_s), (p[2] - 2 * p[1] + p[0]) / dt_s ** 2
        T = truths[1]
        if rolling:
            assert timing is not None
            times = timing.row_time_s(p[1][:, 1], camera.height_px).reshape(4)
            seen, J = _rolling_jacobian(camera, corners_m, T, delta, times)
            velocity = velocity + accel * times[:, None]
        else:
            seen = p[1]
            _, J = residuals_and_jacobian_rt(T.rotation_matrix, T.translation_m, camera.K, corners_m, p[1])
        cov = _tag_corner_covariance(gray, seen, velocity * exposure_s, accel * exposure_s ** 2 / 8, tag_id)
        if cov is None:
            continue
        info += J.T @ np.linalg.solve(cov, J)
        tags += 1
    if tags < 3:
        return np.zeros(0)
    e = rng.multivariate_normal(np.zeros(3), np.linalg.inv(info)[:3, :3], draws)
    return np.degrees(np.linalg.norm(e, axis=1))
