"""The cap's motion over one frame: the velocity prior from past poses and the rolling-shutter fit.

A rolling shutter sees each corner at its row's time (``CameraTiming.row_time_s``): during a fast
glance the top and bottom of the cap are seen several milliseconds apart, and a pose fitted as if
every corner were seen at once is the pose at some mean time of the cap's rows, tilted by the shear.
The joint solver's moving fit (``MovingFit``) solves instead for the pose at the stamp together with
the cap's velocity over the readout (``reprojection.residuals_and_jacobian_moving``), the velocity
held by a prior (``MotionPrior``). A glance speeds up and slows down within a readout: with two past
poses or more the corners are projected with the cap's acceleration as well, the second derivative
of the polynomial through the past poses and the pose being solved (``acceleration``), so that the
top and bottom rows, seen milliseconds before and after the stamp, are not both off the same way by
half the acceleration times their time squared.

The prior comes from the poses of the frames before (the tracker's, ``PastPose``): the velocity at
this frame's stamp is the derivative of the quadratic through the two past poses and the pose being
solved (backward differentiation, BDF2), or of the line through one past pose and it; the prior is
therefore a constraint between this frame's pose and its velocity, not a fixed guess. Its
covariance holds the past poses' covariances and the model's error: the truncation of the finite
difference by the head's angular and linear jerk (two past poses) or acceleration (one), at the
sizes of ``MotionConfig``. With no past pose the prior is a weak one around rest (the speeds of
``MotionConfig``), so a rolling-shutter frame alone still has a pose.

Offline, the frame after is known too (``MotionPrior.following``: the next frame's pose, two-sided):
the velocity and acceleration are then the derivatives of the polynomial through the pose being
solved, up to two past poses and the next one, which interpolates the glance instead of
extrapolating it (a cubic through four poses is off by the head's snap, not its jerk, and by a
share of it a quarter of the backward one's). The live node has no next frame and keeps the
backward prior.

The velocity is held to the prior's (the pose's six unknowns), so the prior's error moves the pose;
how large that error is, the readout itself shows: the corners' residuals along the velocity's
columns, beyond what the pose's absorb, are evidence of it (``MovingFit.prior_error``), and on a
clean frame through a smooth glance they state it smaller than the prior's model does.

A global-shutter frame says nothing of the velocity: its pose is the static fit's, and its velocity
(``static_velocity``) is the prior's finite difference at that pose, with the pose's covariance
propagated into the prior's.

Velocities are twists in ROS order and camera axes: the cap origin's linear velocity (m/s), then
the angular velocity (rad/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.optimize import leastsq

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.camera import CameraModel, CameraTiming
from ficap_ros.geometry.transform import Transform
from ficap_ros.vision.error_bounds import error_bound95
from ficap_ros.vision.motion_blur import blur_modes, blur_px
from ficap_ros.vision.reprojection import (
    TagObservations,
    residuals_and_jacobian_moving,
)
from ficap_ros.vision.uncertainty import (
    UncertaintyConfig,
    combine_uncertainty,
    tag_noise_from_residuals,
    uncertainty_bounds,
    uncertainty_terms,
)

__all__ = ["MotionConfig", "PastPose", "VelocityPrior", "MotionPrior", "MovingFit", "MovingPose",
           "acceleration", "corner_times_s", "moving_pose", "static_velocity"]

#: Reorders the pose solver's (d_theta, d_t) into ROS (t, theta) order.
_POSE_TO_ROS = np.array([3, 4, 5, 0, 1, 2])


@dataclass(frozen=True)
class MotionConfig:
    """How the head moves, for the velocity prior (1-sigma sizes).

    The default jerk and acceleration are the root mean square over a glance under the
    minimum-jerk profile that reaches 250 deg/s in 0.35 s (fast mirror glances); linear sizes are
    the cap origin's, a few centimetres off the axis the head turns about, plus the centripetal
    part. They are what a finite difference of poses may be off by in such a glance. With three
    past poses the jerk is measured instead (the third divided difference through them and the
    pose being solved), at least ``jerk_floor`` times these sizes: slow frames then get the small
    prior error they have.

    Attributes:
        angular_jerk_rad_s3, linear_jerk_m_s3: the third derivative of the cap's orientation
            (rad/s^3) and position (m/s^3): the error of the velocity from two past poses.
        angular_accel_rad_s2, linear_accel_m_s2: the second derivative: the error of the
            velocity from one past pose.
        angular_speed_rad_s, linear_speed_m_s: the velocity itself, for a frame with no past pose
            (a prior around rest).
        angular_snap_rad_s4, linear_snap_m_s4: the fourth derivative: the error of the
            two-sided velocity through two past poses and the next one (its root mean square over
            the same glance).
        jerk_floor: the least measured jerk, as a fraction of the sizes above (the jerk changes
            between the past poses and this frame).
        max_age_s: past (or following) poses further than this from the stamp are not used.
    """

    angular_jerk_rad_s3: float = 500.0
    linear_jerk_m_s3: float = 30.0
    angular_accel_rad_s2: float = 30.0
    linear_accel_m_s2: float = 2.0
    angular_speed_rad_s: float = 4.0
    linear_speed_m_s: float = 0.6
    jerk_floor: float = 0.2
    max_age_s: float = 0.2
    angular_snap_rad_s4: float = 11000.0
    linear_snap_m_s4: float = 660.0

    def __post_init__(self) -> None:
        values = (self.angular_jerk_rad_s3, self.linear_jerk_m_s3, self.angular_accel_rad_s2,
                  self.linear_accel_m_s2, self.angular_speed_rad_s, self.linear_speed_m_s,
                  self.jerk_floor, self.max_age_s, self.angular_snap_rad_s4, self.linear_snap_m_s4)
        if not all(math.isfinite(v) and v > 0.0 for v in values):
            raise ConfigError("motion sizes must be finite and > 0")


@dataclass(frozen=True)
class PastPose:
    """A pose of an earlier (or, offline, the next) frame of the same camera.

    Attributes:
        age_s: how long before this frame's stamp it was, s (> 0 for a frame before; < 0 for the
            frame after, ``MotionPrior.following``: its time relative to the stamp is ``-age_s``).
        T_cam_cap: its pose at its stamp.
        covariance: its 6x6 covariance, ROS order (``CapPose.covariance``).
    """

    age_s: float
    T_cam_cap: Transform
    covariance: np.ndarray


@dataclass(frozen=True)
class VelocityPrior:
    """The prior of the velocity at one candidate pose of this frame.

    Attributes:
        mean: (6,) twist, ROS order.
        d_mean: (6, 6) its derivative by a left perturbation of the pose, columns (d_theta, d_t)
            (the pose solver's order).
        covariance: (6, 6) twist covariance.
        accel: (6,) the acceleration at the stamp, ROS order (m/s^2, then rad/s^2; camera
            axes): the second derivative of the polynomial through the pose and its neighbours
            (``acceleration``); zero with fewer than two.
        d_accel: (6, 6) its derivative by a left perturbation of the pose, as ``d_mean``.
    """

    mean: np.ndarray
    d_mean: np.ndarray
    covariance: np.ndarray
    accel: np.ndarray = field(default_factory=lambda: np.zeros(6))
    d_accel: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))


@dataclass(frozen=True)
class MotionPrior:
    """What the frames before say about this frame's velocity (module docstring).

    Attributes:
        past: up to three past poses, the most recent first (older ones and those beyond
            ``config.max_age_s`` are ignored).
        config: the head's motion sizes.
        following: offline, the next frame's pose (``age_s`` < 0); the prior is then two-sided
            when a past pose is usable too (``two_sided``). Empty live.
    """

    past: tuple[PastPose, ...] = ()
    config: MotionConfig = field(default_factory=MotionConfig)
    following: tuple[PastPose, ...] = ()

    # usable, two_sided and neighbours are cached: the fields are frozen, and the solvers call
    # ``at`` on every iteration.

    @cached_property
    def usable(self) -> tuple[PastPose, ...]:
        """The past poses the prior uses: at most three, each older than the one before."""
        out: list[PastPose] = []
        for p in self.past:
            if len(out) == 3 or not 0.0 < p.age_s <= self.config.max_age_s:
                break
            if out and p.age_s <= out[-1].age_s:
                break
            if not np.all(np.isfinite(p.covariance)):
                break
            out.append(p)
        return tuple(out)

    @property
    def from_past(self) -> bool:
        """Whether a past pose informs the prior (else it is the weak prior around rest)."""
        return bool(self.usable)

    @cached_property
    def two_sided(self) -> bool:
        """Whether the next frame's pose informs the prior with the past ones: a usable past
        pose and a following one within ``config.max_age_s`` with a finite covariance."""
        if not self.following or not self.from_past:
            return False
        nxt = self.following[0]
        return bool(0.0 < -nxt.age_s <= self.config.max_age_s and np.all(np.isfinite(nxt.covariance)))

    @cached_property
    def neighbours(self) -> tuple[PastPose, ...]:
        """The poses the velocity and acceleration come from: two-sided, up to two past poses and
        the next one; otherwise the usable past poses."""
        if self.two_sided:
            return self.usable[:2] + self.following[:1]
        return self.usable

    @cached_property
    def _node_table(self) -> _NodeTable | None:
        """``neighbours``' part of the polynomial through them and a pose (``_make_node_table``):
        the same for every pose the solvers try."""
        return _make_node_table(self.neighbours) if self.neighbours else None

    def at(self, T: Transform) -> VelocityPrior:
        """The prior of the velocity if this frame's pose is ``T``."""
        if self.two_sided:
            return self._two_sided_at(T)
        c = self.config
        past = self.usable  # one-sided: the neighbours, whose table ``_node_table`` holds
        if not past:
            var = np.array([c.linear_speed_m_s] * 3 + [c.angular_speed_rad_s] * 3) ** 2
            return VelocityPrior(np.zeros(6), np.zeros((6, 6)), np.diag(var))
        h1 = past[0].age_s
        times, values, vander_inv = _through_nodes(T, past, self._node_table)
        phi0 = values[0, 3:]  # this pose's rotation in the tangent at the most recent past pose
        if len(past) == 1:
            c0, coefs = 1.0 / h1, (-1.0 / h1,)
            w = phi0 * c0
            v = (T.translation_m - past[0].T_cam_cap.translation_m) * c0
            model = np.array([c.linear_accel_m_s2] * 3 + [c.angular_accel_rad_s2] * 3) * (h1 / 2.0)
        else:
            h2 = past[1].age_s - h1
            c0 = (2.0 * h1 + h2) / (h1 * (h1 + h2))
            c1 = -(h1 + h2) / (h1 * h2)
            c2 = h1 / (h2 * (h1 + h2))
            coefs = (c1, c2)
            w = c0 * phi0 + c2 * values[2, 3:]
            v = (c0 * T.translation_m + c1 * past[0].T_cam_cap.translation_m
                 + c2 * past[1].T_cam_cap.translation_m)
            jerk = np.array([c.linear_jerk_m_s3] * 3 + [c.angular_jerk_rad_s3] * 3)
            if len(past) == 3:
                jerk = np.hypot(_measured_jerk(times, values), c.jerk_floor * jerk)
            model = jerk * (h1 * (h1 + h2) / 6.0)
        cov = np.diag(model**2)
        for coef, p in zip(coefs, past):
            cov = cov + coef * coef * np.asarray(p.covariance, dtype=float)
        jl_inv = _left_jacobian_inverse(phi0)
        accel, a0 = _second_derivative(values, vander_inv) if len(past) >= 2 else (np.zeros(6), 0.0)
        return VelocityPrior(np.concatenate([v, w]), _by_pose(c0, jl_inv), 0.5 * (cov + cov.T),
                             accel, _by_pose(a0, jl_inv))

    def _two_sided_at(self, T: Transform) -> VelocityPrior:
        """``at`` with the next frame's pose: the velocity is the first derivative at the stamp
        of the polynomial through ``T`` and ``neighbours`` (rotations as vectors in the tangent
        at the most recent past pose), its model error the truncation by the head's jerk (three
        poses) or snap (four) at the sizes of ``MotionConfig``."""
        c = self.config
        nodes = self.neighbours
        times, values, vander_inv = _through_nodes(T, nodes, self._node_table)
        weights = vander_inv[1]
        if len(nodes) == 2:
            size = np.array([c.linear_jerk_m_s3] * 3 + [c.angular_jerk_rad_s3] * 3) / 6.0
        else:
            size = np.array([c.linear_snap_m_s4] * 3 + [c.angular_snap_rad_s4] * 3) / 24.0
        cov = np.diag((size * float(np.prod(np.abs(times[1:])))) ** 2)
        for coef, p in zip(weights[1:], nodes):
            cov = cov + coef * coef * np.asarray(p.covariance, dtype=float)
        jl_inv = _left_jacobian_inverse(values[0, 3:])
        accel, a0 = _second_derivative(values, vander_inv)
        return VelocityPrior(weights @ values, _by_pose(float(weights[0]), jl_inv),
                             0.5 * (cov + cov.T), accel, _by_pose(a0, jl_inv))


def _by_pose(coef: np.ndarray | float, jl_inv: np.ndarray) -> np.ndarray:
    """(6, 6) the derivative by a left perturbation of the pose (columns d_theta, d_t) of a twist
    (ROS order) that weighs this frame's pose by ``coef`` in a finite difference of poses."""
    d = np.zeros((6, 6))
    d[0:3, 3:6] = coef * np.eye(3)  # linear by d_t
    d[3:6, 0:3] = coef * jl_inv  # angular by d_theta
    return d


def acceleration(T: Transform, past: tuple[PastPose, ...]) -> tuple[np.ndarray, float]:
    """The cap's acceleration at this frame's stamp (6,: m/s^2 then rad/s^2, ROS order, camera
    axes) if its pose there is ``T``, and the weight of ``T`` in it: the second derivative at the
    stamp of the polynomial through ``T`` and the neighbouring poses ``past`` (``MotionPrior.
    neighbours``: a parabola through two, a cubic through three; rotations as vectors in the
    tangent at the first). Zero with fewer than two (a line has none)."""
    if len(past) < 2:
        return np.zeros(6), 0.0
    _, values, vander_inv = _through_nodes(T, past)
    return _second_derivative(values, vander_inv)


#: (the most recent node's inverse, the times (n + 1,), s, with 0 for the pose, the nodes' values
#: (n, 6), the inverse of the times' Vandermonde matrix): ``_through_nodes``' part that does not
#: depend on the pose.
_NodeTable = tuple[Transform, np.ndarray, np.ndarray, np.ndarray]


def _tangent_value(Ti: Transform, T1_inv: Transform) -> np.ndarray:
    """(6,) a pose's translation, m, then its rotation as a vector in the tangent at the node
    whose inverse is ``T1_inv``, rad."""
    return np.concatenate([Ti.translation_m, (Ti * T1_inv).rvec])


def _make_node_table(nodes: tuple[PastPose, ...]) -> _NodeTable:
    """``_through_nodes``' part that depends on ``nodes`` alone."""
    T1_inv = nodes[0].T_cam_cap.inv()
    times = np.array([0.0] + [-p.age_s for p in nodes])
    values = np.stack([_tangent_value(p.T_cam_cap, T1_inv) for p in nodes])
    return T1_inv, times, values, np.linalg.inv(np.vander(times, increasing=True))


def _through_nodes(T: Transform, nodes: tuple[PastPose, ...],
                   table: _NodeTable | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The polynomial through the pose ``T`` (at 0) and ``nodes`` (at minus their ages): the
    times (n + 1,), s; the values (n + 1, 6): translation, m, then rotation as a vector in the
    tangent at the first node, rad; and the inverse of the times' Vandermonde matrix (increasing
    powers), whose row k weighs the values into the coefficient of t^k. ``table``: ``nodes``'
    ``_make_node_table`` when the caller keeps it."""
    T1_inv, times, node_values, vander_inv = table if table is not None else _make_node_table(nodes)
    values = np.concatenate([_tangent_value(T, T1_inv)[None], node_values])
    return times, values, vander_inv


def _second_derivative(values: np.ndarray, vander_inv: np.ndarray) -> tuple[np.ndarray, float]:
    """p''(0) = 2 a_2 of the polynomial p(t) = sum a_k t^k through the nodes' ``values``
    (``_through_nodes``), and the weight of the first value (this frame's pose) in it."""
    weights = 2.0 * vander_inv[2]
    return weights @ values, float(weights[0])


def _measured_jerk(times: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(6,) the magnitude of each twist component's second derivative (the jerk of position and
    orientation): six times the third divided difference through the four nodes' ``times`` (4,)
    and ``values`` (4, 6) (``_through_nodes``: the pose at 0 and three past poses)."""
    t = times.tolist()
    rows = list(values)
    for level in range(1, 4):  # Newton's divided differences, in place
        rows = [(rows[i] - rows[i + 1]) / (t[i] - t[i + level]) for i in range(len(rows) - 1)]
    return np.abs(6.0 * rows[0])


def _left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """(3, 3) derivative of ``log(exp(d) exp(phi))`` by ``d`` at 0: how a rotation vector moves
    when its rotation is turned a little more (camera axes)."""
    theta = float(np.linalg.norm(phi))
    k = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if theta < 1e-6:
        return np.eye(3) - 0.5 * k + k @ k / 12.0
    coef = 1.0 / theta**2 - (1.0 + math.cos(theta)) / (2.0 * theta * math.sin(theta))
    return np.eye(3) - 0.5 * k + coef * (k @ k)


def static_velocity(prior: MotionPrior, T: Transform,
                    covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """A global-shutter frame's velocity: the prior's finite difference at its pose ``T`` (with
    ``covariance``, 6x6 ROS order), and its covariance (the prior's plus the pose's, propagated).
    None without a past pose (no velocity is measured)."""
    if not prior.from_past or not np.all(np.isfinite(covariance)):
        return None
    vp = prior.at(T)
    D = vp.d_mean[:, _POSE_TO_ROS]  # by (t, theta), ROS order
    cov = vp.covariance + D @ covariance @ D.T
    return vp.mean, 0.5 * (cov + cov.T)


class MovingFit:
    """The joint solver's fit of a cap moving over a rolling shutter's readout.

    With a past pose (``MotionPrior.from_past``) the velocity is the prior's: its finite
    difference at the pose being fitted, so the fit has the pose's six unknowns and each corner
    is projected from the pose moved at that velocity to its time. The corners themselves say
    little about the velocity over one readout (a shear between rows a fraction of a pixel at the
    cap's size), and what they say shares their biases: a vertical scale error of the corners
    reads as a vertical velocity, and through it as depth. The prior's error is propagated into
    the pose's covariance instead (``motion_term``).

    Without a past pose the prior is the weak one around rest, and the velocity is fitted with the
    pose: 12 unknowns, the pose's left perturbation and translation then the velocity in twist
    order; residuals: the corners' reprojection at their times and the prior's six rows whitened
    by its covariance and scaled by ``sigma_px``, the corner noise (px) that puts them in the
    corners' units (the least-squares cost is the negative log posterior times ``sigma_px ** 2``).
    ``sigma_px`` is re-estimated from each fit's residuals (the median tag's, as
    ``uncertainty.tag_noise_px``).

    The state (``velocity``, ``sigma_px``) is that of the last ``refine`` or ``reweighted``.
    """

    #: Corner noise before any fit, and the least it is taken to be, px.
    START_SIGMA_PX = 0.15
    MIN_SIGMA_PX = 0.03

    def __init__(self, prior: MotionPrior) -> None:
        self.prior = prior
        self.held = prior.from_past
        self.sigma_px = self.START_SIGMA_PX
        self.velocity: np.ndarray | None = None

    @property
    def unknowns(self) -> int:
        """6 (the pose; the velocity held to the prior) or 12 (pose and velocity)."""
        return 6 if self.held else 12

    def begin(self, T: Transform) -> None:
        """Start from the prior's velocity at the start pose ``T``."""
        self.velocity = self.prior.at(T).mean.copy()

    def _velocity(self, T: Transform) -> np.ndarray:
        if self.held or self.velocity is None:
            self.begin(T)
        assert self.velocity is not None
        return self.velocity

    def _accel(self, T: Transform) -> np.ndarray | None:
        """The acceleration the corners are projected with: held, the prior's at ``T``; fitted
        (no past pose), none."""
        return self.prior.at(T).accel if self.held else None

    def _step(self, T0: Transform, velocity0: np.ndarray, x: np.ndarray) -> tuple[Transform, np.ndarray]:
        """The pose and velocity at the unknowns ``x`` around (T0, velocity0)."""
        T = T0.turned(x[:3], x[3:6])
        return T, (self.prior.at(T).mean if self.held else velocity0 + x[6:])

    def prior_rows(self, T: Transform, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The prior's residuals (6,) and their Jacobian (6, 12) at pose ``T`` and ``velocity``:
        ``sigma_px`` times the prior's whitened misfit."""
        vp = self.prior.at(T)
        try:
            C = np.linalg.cholesky(vp.covariance)
        except np.linalg.LinAlgError:
            C = np.diag(np.sqrt(np.maximum(np.diagonal(vp.covariance), 1e-18)))
        S = self.sigma_px * np.linalg.inv(C)
        jac = np.empty((6, 12))
        jac[:, :6] = -S @ vp.d_mean
        jac[:, 6:] = S
        return S @ (velocity - vp.mean), jac

    def residuals_and_jacobian(self, obs: TagObservations, T: Transform,
                               velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The fit's residuals and Jacobian (columns: ``unknowns``): held, the corners' (2N,),
        the velocity following the pose; else the corners' and the prior's (2N + 6,)."""
        if self.held:
            vp = self.prior.at(T)
            res, J = residuals_and_jacobian_moving(T.rotation_matrix, T.translation_m, velocity,
                                                   obs, vp.accel)
            # The acceleration's columns are the velocity's times tau / 2 (moving_points_m).
            half_tau = 0.5 * np.repeat(np.asarray(obs.time_s, dtype=float).reshape(-1), 2)
            return res, J[:, :6] + J[:, 6:] @ vp.d_mean + (half_tau[:, None] * J[:, 6:]) @ vp.d_accel
        res, J = residuals_and_jacobian_moving(T.rotation_matrix, T.translation_m, velocity, obs)
        rp, Jp = self.prior_rows(T, velocity)
        return np.concatenate([res, rp]), np.vstack([J, Jp])

    def refine(self, obs: TagObservations, T0: Transform) -> tuple[Transform, float]:
        """Least-squares fit from ``T0`` (MINPACK's Levenberg-Marquardt, as the static fit);
        returns (pose at the stamp, rms_px of the corners). Updates ``velocity`` and
        ``sigma_px``."""
        velocity0 = self._velocity(T0)
        x0 = np.concatenate([np.zeros(3), T0.translation_m, np.zeros(self.unknowns - 6)])
        cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

        def both(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            key = x.tobytes()
            if key not in cache:
                cache.clear()
                cache[key] = self.residuals_and_jacobian(obs, *self._step(T0, velocity0, x))
            return cache[key]

        x, _cov, info, _msg, _status = leastsq(
            lambda x: both(x)[0], x0, Dfun=lambda x: both(x)[1], full_output=True,
            ftol=1e-10, xtol=1e-10, gtol=1e-8, maxfev=50, factor=100.0)
        T, self.velocity = self._step(T0, velocity0, x)
        res = info["fvec"][: 8 * len(obs)]
        self.sigma_px = self._noise_px(res, len(obs))
        return T, float(np.sqrt(np.mean(res**2) * 2.0))

    def _noise_px(self, res: np.ndarray, n_tags: int) -> float:
        rms = np.sqrt(np.mean(res.reshape(n_tags, 8) ** 2, axis=1))
        return max(math.sqrt(2.0) * float(np.median(rms)), self.MIN_SIGMA_PX)

    def errors(self, obs: TagObservations, T: Transform) -> np.ndarray:
        """Per-tag RMS reprojection error (T,), px, at pose ``T`` moving at the current velocity
        (held: the prior's at ``T``)."""
        res, _ = residuals_and_jacobian_moving(T.rotation_matrix, T.translation_m,
                                               self._velocity(T), obs, self._accel(T))
        return np.sqrt(np.sum(res.reshape(len(obs), 4, 2) ** 2, axis=2).mean(axis=1))

    def corner_residuals(self, obs: TagObservations, T: Transform) -> tuple[np.ndarray, np.ndarray]:
        """The corners' residuals (2N,) and the fit's Jacobian of them (2N, ``unknowns``)."""
        res, J = self.residuals_and_jacobian(obs, T, self._velocity(T))
        n = 8 * len(obs)
        return res[:n], J[:n]

    def reweighted(self, obs: TagObservations, T: Transform,
                   tag_sigma_px: np.ndarray) -> Transform:
        """One weighted Gauss-Newton step (each tag by its corner noise ``tag_sigma_px``, relative
        to the median tag's) from the unweighted optimum ``T``; updates ``velocity``."""
        velocity = self._velocity(T)
        res, J = self.residuals_and_jacobian(obs, T, velocity)
        w = np.concatenate([self._weights(tag_sigma_px), np.ones(len(res) - 8 * len(obs))])
        try:
            dx = -np.linalg.solve(J.T @ (w[:, None] * J), J.T @ (w * res))
        except np.linalg.LinAlgError:
            return T
        if not np.all(np.isfinite(dx)):
            return T
        x = np.concatenate([dx[:3], T.translation_m + dx[3:6], dx[6:]])
        T, self.velocity = self._step(T, velocity, x)
        return T

    @staticmethod
    def _weights(tag_sigma_px: np.ndarray) -> np.ndarray:
        rel = np.asarray(tag_sigma_px, dtype=float) / max(float(np.median(tag_sigma_px)), 1e-12)
        return np.repeat(1.0 / rel**2, 8)

    def prior_information(self, T: Transform) -> np.ndarray | None:
        """What the prior adds to the fit's normal matrix (12, 12; px units), None when held."""
        if self.held:
            return None
        Jp = self.prior_rows(T, self._velocity(T))[1]
        return Jp.T @ Jp

    def motion_term(self, obs: TagObservations, T: Transform,
                    tag_sigma_px: np.ndarray | None) -> np.ndarray:
        """(6, 6) ROS order: the pose covariance the prior's own error causes, through the
        (weighted: ``tag_sigma_px``, None: equal weights) fit. Held: the corners were projected
        at the prior's velocity, so its error moves the pose as the corners' response to it, at
        the size the readout leaves it (``prior_error``); fitted: the prior's rows are noise of
        variance ``sigma_px ** 2`` each."""
        velocity = self._velocity(T)
        n = 8 * len(obs)
        w = np.ones(n) if tag_sigma_px is None else self._weights(tag_sigma_px)
        res, J = self.residuals_and_jacobian(obs, T, velocity)
        H = J[:n].T @ (w[:, None] * J[:n])
        if self.held:
            _, J12 = residuals_and_jacobian_moving(T.rotation_matrix, T.translation_m, velocity,
                                                   obs, self._accel(T))
            G = -np.linalg.solve(H, J[:n].T @ (w[:, None] * J12[:, 6:]))
            noise_px = max(float(np.median(np.sqrt(np.mean(res[:n].reshape(-1, 8) ** 2, axis=1)))), 1e-4)
            cov = G @ self.prior_error(res[:n], J12, w, self.prior.at(T).covariance, noise_px) @ G.T
        else:
            Jp = J[n:]
            M = np.linalg.inv(H + Jp.T @ Jp)
            cov = (self.sigma_px**2 * M @ Jp.T @ Jp @ M)[:6, :6]
        cov = cov[np.ix_(_POSE_TO_ROS, _POSE_TO_ROS)]
        return 0.5 * (cov + cov.T)

    @staticmethod
    def prior_error(res: np.ndarray, J12: np.ndarray, w: np.ndarray, prior_covariance: np.ndarray,
                    noise_px: float) -> np.ndarray:
        """(6, 6) the second moment of the held velocity's error (the prior's mean less the true
        velocity, twist order) given what the readout says of it.

        The corners of a rolling shutter's rows, seen over the readout, carry evidence of the
        velocity beyond the prior's: the part of their residuals ``res`` (2N,, at the held
        velocity) the velocity's columns of ``J12`` (2N, 12: ``residuals_and_jacobian_moving``)
        explain and the pose's do not, with the median tag's noise per coordinate ``noise_px``
        and the tags' weights ``w`` (2N,, 1 for the median tag; ``motion_term`` takes the noise
        from the residuals' root mean square). The prior's error then has the posterior
        covariance ``(P^-1 + I)^-1`` (``P``
        the prior's covariance, ``I`` the readout's information) and the posterior mean ``d``;
        its second moment is ``d d^T`` plus that covariance. Where the prior states its error
        right this is ``P`` on average; where the readout shows the velocity better than the prior
        states it, it is what the readout leaves. The held pose does not use the evidence: its
        velocity stays the prior's, and only the size of its error follows it."""
        Jp, Jv = J12[:, :6], J12[:, 6:]
        wv, wp = w[:, None] * Jv, w[:, None] * Jp
        try:
            Hp_inv_pv = np.linalg.solve(Jp.T @ wp, Jp.T @ wv)  # (6, 6)
            info = (Jv.T @ wv - (Jp.T @ wv).T @ Hp_inv_pv) / noise_px**2
            score = (wv.T @ res - Hp_inv_pv.T @ (wp.T @ res)) / noise_px**2
            posterior = np.linalg.inv(np.linalg.inv(prior_covariance) + 0.5 * (info + info.T))
        except np.linalg.LinAlgError:
            return prior_covariance
        mean = -posterior @ score
        moment = posterior + np.outer(mean, mean)
        if not np.all(np.isfinite(moment)):
            return prior_covariance
        return 0.5 * (moment + moment.T)

    def velocity_covariance(self, obs: TagObservations, T: Transform, tag_sigma_px: np.ndarray,
                            pose_covariance: np.ndarray, inflation: float = 1.0) -> np.ndarray:
        """(6, 6) covariance of the velocity. Held: the prior's at the pose with the pose's
        covariance (ROS order) propagated (``static_velocity``'s); fitted: each tag's corner noise
        ``tag_sigma_px`` (times ``inflation``) and the prior through the (weighted) fit."""
        velocity = self._velocity(T)
        if self.held:
            vp = self.prior.at(T)
            D = vp.d_mean[:, _POSE_TO_ROS]
            cov = vp.covariance + D @ pose_covariance @ D.T
            return 0.5 * (cov + cov.T)
        res, J = residuals_and_jacobian_moving(T.rotation_matrix, T.translation_m, velocity, obs)
        _, Jp = self.prior_rows(T, velocity)
        var = np.repeat((inflation * np.asarray(tag_sigma_px, dtype=float)) ** 2, 8)
        # The prior rows are whitened to variance sigma_px ** 2; the corners' weights are 1 / var.
        H = J.T @ (J / var[:, None]) + Jp.T @ Jp / self.sigma_px**2
        try:
            cov = np.linalg.inv(H)[6:, 6:]
        except np.linalg.LinAlgError:
            return self.prior.at(T).covariance
        return 0.5 * (cov + cov.T)


def corner_times_s(corners_px: dict[int, np.ndarray], camera: CameraModel,
                   timing: CameraTiming) -> dict[int, np.ndarray]:
    """Each undistorted corner's time (4,) per id, s from the stamp: the time of the row of the
    (distorted) image it was seen in (``CameraTiming.row_time_s``)."""
    ids = list(corners_px)
    px = np.concatenate([corners_px[i] for i in ids])
    if camera.is_distorted:
        rays = np.column_stack([px, np.ones(len(px))]) @ np.linalg.inv(camera.K).T
        px = camera.project(rays)
    times = timing.row_time_s(px[:, 1], camera.height_px).reshape(-1, 4)
    return dict(zip(ids, times))


@dataclass(frozen=True)
class MovingPose:
    """A moving cap's reported pose (``moving_pose``): at the stamp, with its velocity.

    Attributes:
        T_cam_cap: the pose at the stamp.
        velocity: (6,) twist, ROS order; velocity_covariance: its 6x6 covariance.
        rms_px: RMS reprojection error of the corners at their times, px.
        covariance, rot_err95_deg, trans_err95_mm: as ``CapPose``'s (NaN without uncertainty).
    """

    T_cam_cap: Transform
    velocity: np.ndarray
    velocity_covariance: np.ndarray
    rms_px: float
    covariance: np.ndarray
    rot_err95_deg: float
    trans_err95_mm: float


def moving_pose(fit: MovingFit, used: TagObservations, T: Transform, edge_shift_px: np.ndarray,
                config: UncertaintyConfig, with_uncertainty: bool,
                exposure_s: float = 0.0) -> MovingPose:
    """The reported pose of a moving cap's solution ``T`` on the tags ``used``: each tag weighted
    by its corner noise (``config.weight_tags``, four tags or more), its rms, its covariance (the
    velocity marginalised out and the prior's error in: ``uncertainty_terms``) and bounds, and the
    velocity with its covariance. ``edge_shift_px``: the tags' cell-fit edge shifts;
    ``exposure_s``: the exposure (0: not known), for the motion blur's term."""
    res, _ = fit.corner_residuals(used, T)
    tag_sigma = tag_noise_from_residuals(res, len(used))
    weighted = config.weight_tags and len(used) >= 4
    if weighted:
        T = fit.reweighted(used, T, tag_sigma)
    res, J = fit.corner_residuals(used, T)
    rms = float(np.sqrt(np.mean(res**2) * 2.0))
    covariance = velocity_cov = np.full((6, 6), np.nan)
    rot95 = trans95 = float("nan")
    if with_uncertainty:
        weights = tag_sigma if weighted else None
        assert fit.velocity is not None
        modes = (blur_modes(used.image_px, blur_px(used, T, fit.velocity, exposure_s))
                 if exposure_s > 0.0 else None)
        terms, seen = uncertainty_terms(
            used, T, weights, edge_shift_px, at=(res, J),
            prior_information=fit.prior_information(T),
            motion_term=fit.motion_term(used, T, weights), shared_modes=modes)
        covariance = combine_uncertainty(terms, seen, config)
        rot95, trans95 = error_bound95(covariance,
                                       *uncertainty_bounds(terms, seen, config, covariance))
        velocity_cov = fit.velocity_covariance(used, T, tag_sigma, covariance,
                                               config.residual_inflation)
    assert fit.velocity is not None
    return MovingPose(T, np.array(fit.velocity), velocity_cov, rms, covariance, rot95, trans95)
