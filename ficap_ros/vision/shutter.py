"""A camera's timing read from its frames, for recordings that do not say it.

Readout (rolling shutter): a frame fitted as if every row were seen at once leaves a pattern in
its corner residuals when the cap moves: each corner sits where the cap was at its row's time,
``row_time_s(y) = (y + 0.5 - H / 2) / H * readout``, so it is displaced by that time times its own
image velocity (the velocity of the frames before: ``CapPose.velocity``). The static pose takes up
the part of that pattern a rigid pose can (the shear of a turning cap is only partly a rigid
motion); the rest stays in the residuals, in proportion to the readout. Each moving frame's
residuals give the readout by least squares on that remainder, with its variance from the
residuals' own scatter (``readout_evidence``); frames are combined by their information
(``combine_evidence``). The sign says the row order: positive top to bottom.

Exposure (motion blur): each moving tag's smear along its image motion, as the corner stage's
photometric fit measures it, over that motion's speed (``TimingEvidence.exposure2_s2`` holds its
square, which the smear's variance measures linearly).

Both need a moving cap: a frame whose cap is still says nothing, and its evidence is None.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ficap_ros.geometry.camera import CameraModel
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.pose_kernels import corner_rate_px_s
from ficap_ros.vision.reprojection import (
    TagObservations,
    residuals_and_jacobian,
    rotations_of,
)

__all__ = ["TimingEvidence", "TimingEstimate", "readout_evidence", "frame_evidence",
           "combine_evidence"]

#: Least image speed of the cap's corners, px/s, for a frame to give evidence: slower, a 30 ms
#: readout or exposure moves them by a fraction of the corners' noise.
MIN_SPEED_PX_S = 60.0

#: ``speed_bound_px_s`` below this share of ``MIN_SPEED_PX_S`` skips a frame: the bound is exact
#: arithmetic's, the share keeps floating-point rounding (relative 1e-13 at most) far inside it.
_BOUND_MARGIN = 0.99


@dataclass(frozen=True)
class TimingEvidence:
    """What one frame says of the camera's timing (each part None when it says nothing).

    Attributes:
        readout_s, readout_var_s2: the readout (signed: negative bottom to top) and its variance.
        exposure2_s2, exposure2_var_s4: the exposure's square and its variance (the square is
            what edge widths measure linearly; it may come out negative for a short exposure).
    """

    readout_s: float | None = None
    readout_var_s2: float | None = None
    exposure2_s2: float | None = None
    exposure2_var_s4: float | None = None


@dataclass(frozen=True)
class TimingEstimate:
    """The camera's timing from the evidence of many frames (``combine_evidence``).

    Attributes:
        readout_ms, readout_se_ms: the readout (signed: negative bottom to top) and its standard
            error, ms; None without evidence.
        exposure_ms, exposure_se_ms: the exposure and its standard error, ms; None without
            evidence.
        readout_frames, exposure_frames: how many frames gave evidence.
    """

    readout_ms: float | None
    readout_se_ms: float | None
    exposure_ms: float | None
    exposure_se_ms: float | None
    readout_frames: int
    exposure_frames: int

    def as_dict(self) -> dict[str, float | int | None]:
        """The fields by name (summary.json)."""
        return {k: getattr(self, k) for k in ("readout_ms", "readout_se_ms", "exposure_ms",
                                               "exposure_se_ms", "readout_frames",
                                               "exposure_frames")}


def _corner_velocity_px_s(obs: TagObservations, T: Transform, velocity: np.ndarray) -> np.ndarray:
    """(N, 2) each corner's image velocity, px/s, of a cap at ``T`` moving at ``velocity``: the
    central difference of the corners' pinhole projections (camera frame) at the times -eps and
    +eps (``moving_points_m``'s motion; the projections and difference compiled,
    ``pose_kernels.corner_rate_px_s``)."""
    eps = 1e-3
    Y = obs.model_m.reshape(-1, 3) @ T.rotation_matrix.T
    tau = np.array([[-eps], [eps]])
    turn, shift = tau * velocity[3:], tau * velocity[:3]
    return corner_rate_px_s(Y, rotations_of(turn), shift, T.translation_m,
                            np.asarray(obs.K, dtype=np.float64), 2 * eps)


def speed_bound_px_s(obs: TagObservations, T: Transform, velocity: np.ndarray) -> float:
    """An upper bound, px/s, of every corner's ``_corner_velocity_px_s`` speed (inf where a
    corner may reach the camera's plane), from norms alone: over the difference's times a
    point Y + t (camera frame, Y = R X) moving at ``velocity`` (v, w) moves at
    |v + w x E Y| <= |v| + |w| |Y|, stays within |Y| + |t| + eps |v| of the camera and at a
    depth of at least z(0) less its travel; a pinhole's image speed is at most
    sqrt((|fx| + |s|)^2 + fy^2) |dP/dt| |P| / z^2, and a central difference is the mean of the
    derivative over its interval. Lets a still cap skip the projections."""
    eps = 1e-3
    Y = obs.model_m.reshape(-1, 3) @ T.rotation_matrix.T
    y = np.sqrt((Y * Y).sum(axis=1))
    v, w = float(np.linalg.norm(velocity[:3])), float(np.linalg.norm(velocity[3:]))
    rate = v + w * y
    z = Y[:, 2] + T.translation_m[2] - eps * rate
    if not np.all(z > 0.0):
        return math.inf
    K = obs.K
    gain = math.hypot(abs(K[0, 0]) + abs(K[0, 1]), K[1, 1])
    reach = y + float(np.linalg.norm(T.translation_m)) + eps * v
    return float((gain * rate * reach / (z * z)).max())


def readout_evidence(obs: TagObservations, T: Transform, velocity: np.ndarray,
                     rows_px: np.ndarray, height_px: int) -> tuple[float, float] | None:
    """(readout_s, variance) from a static fit ``T`` of ``obs`` (corners seen at the distorted
    rows ``rows_px`` (N,)) whose cap moves at ``velocity``; None for a still cap or too few
    corners."""
    # A cap too slow by the bound cannot pass the speed test below: skip its projections.
    if len(obs) < 2 or speed_bound_px_s(obs, T, velocity) < _BOUND_MARGIN * MIN_SPEED_PX_S:
        return None
    res, J = residuals_and_jacobian(T, obs)
    speed = _corner_velocity_px_s(obs, T, velocity)
    n = len(res)
    if float(np.linalg.norm(speed, axis=1).max()) < MIN_SPEED_PX_S:
        return None
    frac = (np.asarray(rows_px, dtype=float) + 0.5 - 0.5 * height_px) / float(height_px)
    pattern = (speed * frac[:, None]).reshape(-1)
    # The part of the pattern a rigid pose cannot take up: its residual after projecting out J.
    coef, *_ = np.linalg.lstsq(J, pattern, rcond=None)
    m = pattern - J @ coef
    mm = float(m @ m)
    if mm <= 0.0:
        return None
    # A readout r displaces the corners by r * pattern; res = projection - observation.
    r = -float(m @ res) / mm
    left = res + r * m
    dof = n - J.shape[1] - 1
    sigma2 = float(left @ left) / max(dof, 1)
    return r, sigma2 / mm


def frame_evidence(obs: TagObservations, T: Transform, velocity: np.ndarray,
                   camera: CameraModel, rows_px: np.ndarray) -> TimingEvidence | None:
    """One global-shutter fit's ``TimingEvidence`` of the readout, or None."""
    r = readout_evidence(obs, T, velocity, rows_px, camera.height_px)
    return None if r is None else TimingEvidence(r[0], r[1])


def _weighted(values: list[tuple[float, float]]) -> tuple[float, float] | None:
    """Inverse-variance mean and its standard error, the variances scaled up by the values'
    own scatter about the mean when that exceeds them (chi-square per degree of freedom)."""
    vals = [(v, var) for v, var in values if var is not None and var > 0.0 and math.isfinite(v)]
    if not vals:
        return None
    w = np.array([1.0 / var for _, var in vals])
    x = np.array([v for v, _ in vals])
    mean = float((w * x).sum() / w.sum())
    chi2 = float((w * (x - mean) ** 2).sum()) / max(len(x) - 1, 1)
    return mean, math.sqrt(max(chi2, 1.0) / w.sum())


def combine_evidence(evidence: Sequence[TimingEvidence | None]) -> TimingEstimate:
    """The camera's timing from the frames' evidence (inverse-variance means)."""
    got = [e for e in evidence if e is not None]
    r = _weighted([(e.readout_s, e.readout_var_s2) for e in got if e.readout_s is not None])
    x = _weighted([(e.exposure2_s2, e.exposure2_var_s4) for e in got if e.exposure2_s2 is not None])
    readout = (None, None) if r is None else (r[0] * 1e3, r[1] * 1e3)
    if x is None:
        exposure: tuple[float | None, float | None] = (None, None)
    else:
        value = math.sqrt(max(x[0], 0.0))
        # d sqrt(x) = dx / (2 sqrt(x)); at zero, the square root of the square's error.
        se = x[1] / (2.0 * value) if value > math.sqrt(x[1]) else math.sqrt(x[1])
        exposure = (value * 1e3, se * 1e3)
    return TimingEstimate(readout[0], readout[1], exposure[0], exposure[1],
                          sum(e.readout_s is not None for e in got),
                          sum(e.exposure2_s2 is not None for e in got))
