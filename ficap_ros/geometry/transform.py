"""Rigid transforms with the frames in their names.

``T_a_b`` is the pose of frame b in frame a: it maps a point from b coordinates into a coordinates,
``p_a = R_a_b p_b + t_a_b``. Rotations are ``scipy.spatial.transform.Rotation``; quaternions that
cross an interface are named for their order: ``q_wxyz`` (ROS messages store x, y, z, w fields;
our CSV columns are w, x, y, z) or ``q_xyzw`` (scipy's order).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError

__all__ = ["Transform", "CAM_FROM_FORWARD", "rotate_covariance", "compose", "inverse", "from_rotvec"]

# Rotation's own Cython kernels (scipy 1.17, pinned): ``compose``, ``inverse`` and ``from_rotvec``
# call the functions ``Rotation``'s operators call, on the same numbers, without its array-API
# dispatch and argument promotion (~7 of a composition's ~9 us; a tracked frame and its labels
# compose ~20 rotations). Bit-identical quaternions (test_transform checks them against the
# operators); private, so optional: without it, or for anything but single numpy rotations, the
# operators themselves.
try:
    from scipy.spatial.transform import _rotation_cy as _KERNELS

    _IDENTITY = Rotation.identity()
    _XP = _IDENTITY._xp
    _FAST = _IDENTITY._backend is _KERNELS and _IDENTITY._single
except (ImportError, AttributeError):  # pragma: no cover - another scipy
    _FAST = False


def _single(quat: np.ndarray) -> Rotation:
    """A single Rotation holding ``quat`` (1, 4), as ``Rotation._from_raw_quat`` builds one (its
    own ``atleast_nd`` is a third of an inversion's time)."""
    rot = Rotation.__new__(Rotation)
    rot._single, rot._quat, rot._xp, rot._backend = True, quat, _XP, _KERNELS
    return rot


def _fast(*rotations: Rotation) -> bool:
    return _FAST and all(type(r) is Rotation and r._single and r._backend is _KERNELS for r in rotations)


def compose(a: Rotation, b: Rotation) -> Rotation:
    """``a * b`` (apply b, then a) of single rotations: the same quaternion as the operator."""
    if not _fast(a, b):
        return a * b
    q = _KERNELS.from_quat(_KERNELS.compose_quat(a._quat, b._quat), normalize=True, copy=False,
                           scalar_first=False)
    return _single(q)


def inverse(a: Rotation) -> Rotation:
    """``a.inv()`` of a single rotation: the same quaternion."""
    if not _fast(a):
        return a.inv()
    return _single(_KERNELS.inv(a._quat))


def from_rotvec(rotvec_rad: np.ndarray) -> Rotation:
    """``Rotation.from_rotvec`` of one rotation vector (3,), rad: the same quaternion."""
    rv = np.asarray(rotvec_rad, dtype=np.float64)
    if not _FAST or rv.shape != (3,):
        return Rotation.from_rotvec(rv)
    return _single(_KERNELS.from_rotvec(rv[None], degrees=False))


def _apply(a: Rotation, vector: np.ndarray) -> np.ndarray:
    """``a.apply(vector)`` of one vector (3,) by a single rotation: the same numbers."""
    if not _fast(a):
        return a.apply(vector)
    return _KERNELS.apply(a._quat, np.asarray(vector, dtype=np.float64).reshape(1, 3), inverse=False)[0]


def _kernels_agree() -> bool:
    """The kernels take these arguments and give the operators' numbers (checked once, at
    import: a scipy whose private kernels changed falls back to the operators, not to errors)."""
    try:
        a, b = Rotation.from_rotvec([0.1, -0.2, 0.3]), Rotation.from_rotvec([-0.3, 0.1, 0.2])
        v = np.array([0.5, -1.0, 2.0])
        return bool(np.array_equal(compose(a, b).as_quat(), (a * b).as_quat())
                    and np.array_equal(inverse(a).as_quat(), a.inv().as_quat())
                    and np.array_equal(from_rotvec([0.1, -0.2, 0.3]).as_quat(), a.as_quat())
                    and np.array_equal(_apply(a, v), a.apply(v)))
    except (TypeError, ValueError, AttributeError):  # pragma: no cover - another scipy
        return False


_FAST = _FAST and _kernels_agree()


@dataclass(frozen=True)
class Transform:
    """A rigid transform ``T_a_b``: rotation and translation in metres."""

    rotation: Rotation
    translation_m: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.translation_m, dtype=np.float64).reshape(3).copy()
        t.setflags(write=False)
        object.__setattr__(self, "translation_m", t)

    @classmethod
    def identity(cls) -> Transform:
        return cls(Rotation.identity(), np.zeros(3))

    @classmethod
    def from_rvec_tvec(cls, rvec: np.ndarray, tvec_m: np.ndarray) -> Transform:
        """From OpenCV's rotation vector (rad) and translation (m)."""
        return cls(Rotation.from_rotvec(np.asarray(rvec, dtype=np.float64).reshape(3)), tvec_m)

    @classmethod
    def from_matrix(cls, matrix: np.ndarray) -> Transform:
        """From a 4x4 homogeneous matrix (translation in metres)."""
        m = np.asarray(matrix, dtype=np.float64)
        return cls(Rotation.from_matrix(m[:3, :3]), m[:3, 3])

    @classmethod
    def from_xyz_q_xyzw(cls, values: "list[float] | tuple[float, ...] | np.ndarray",
                        name: str = "transform") -> Transform:
        """From the 7 numbers of ``static_transform_publisher``: x y z (m) qx qy qz qw.

        As there, the numbers are the pose of the child frame in the parent frame (``T_parent_child``).
        The quaternion is normalised when its norm is within 1e-3 of 1 (YAML rounding).

        Raises:
            ConfigError: not 7 finite numbers, or a quaternion that is not unit length.
        """
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        if v.size != 7 or not np.all(np.isfinite(v)):
            raise ConfigError(f"{name} must be 7 finite numbers: x y z (m) qx qy qz qw")
        norm = float(np.linalg.norm(v[3:]))
        if abs(norm - 1.0) > 1e-3:
            raise ConfigError(f"{name} quaternion (qx qy qz qw) must be unit length, norm {norm:.6g}")
        return cls(Rotation.from_quat(v[3:] / norm), v[:3])

    @property
    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix, translation in metres."""
        m = np.eye(4)
        m[:3, :3] = self.rotation.as_matrix()
        m[:3, 3] = self.translation_m
        return m

    @property
    def rvec(self) -> np.ndarray:
        """OpenCV rotation vector, rad."""
        return self.rotation.as_rotvec()

    @property
    def q_wxyz(self) -> np.ndarray:
        """Unit quaternion (w, x, y, z), w >= 0."""
        x, y, z, w = self.rotation.as_quat(canonical=True)
        return np.array([w, x, y, z])

    @property
    def q_xyzw(self) -> np.ndarray:
        """Unit quaternion (x, y, z, w), w >= 0 (scipy's and ROS message field order)."""
        return self.rotation.as_quat(canonical=True)

    def __mul__(self, other: Transform) -> Transform:
        """Compose: ``T_a_b * T_b_c = T_a_c``."""
        return Transform(
            compose(self.rotation, other.rotation),
            _apply(self.rotation, np.array(other.translation_m)) + self.translation_m,
        )

    def inv(self) -> Transform:
        r_inv = inverse(self.rotation)
        return Transform(r_inv, -_apply(r_inv, np.array(self.translation_m)))

    @cached_property
    def rotation_matrix(self) -> np.ndarray:
        """3x3 rotation matrix R_a_b (read-only; computed once: the pose code applies it often)."""
        m = self.rotation.as_matrix()
        m.setflags(write=False)
        return m

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points (..., 3) from frame b into frame a (same length unit as the translation)."""
        pts = np.asarray(points, dtype=np.float64)
        return (pts.reshape(-1, 3) @ self.rotation_matrix.T + self.translation_m).reshape(pts.shape)


#: Rotation of a REP-103 body frame (x forward, y left, z up) whose x axis looks along the camera's
#: optical axis, expressed in the camera optical frame (x right, y down, z forward): R_cam_forward.
CAM_FROM_FORWARD = Rotation.from_matrix(
    np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
)


def rotate_covariance(covariance: np.ndarray, rotation: Rotation) -> np.ndarray:
    """A 6x6 pose covariance (ROS order: x y z, rotation about x y z, both in the parent frame's
    axes) re-expressed in a parent frame rotated by ``rotation`` (R_new_old): each 3x3 block is
    conjugated by R, so variances move with the axes and the total is unchanged."""
    R = rotation.as_matrix()
    B = np.zeros((6, 6))
    B[:3, :3] = R
    B[3:, 3:] = R
    return B @ np.asarray(covariance, dtype=np.float64).reshape(6, 6) @ B.T
