"""Rigid transforms with the frames in their names.

``T_a_b`` is the pose of frame b in frame a: it maps a point from b coordinates into a coordinates,
``p_a = R_a_b p_b + t_a_b``. Rotations that cross an interface are
``scipy.spatial.transform.Rotation``; quaternions are named for their order: ``q_wxyz`` (our CSV
columns; scipy's ``scalar_first=True``) or ``q_xyzw`` (ROS message fields, scipy's default).

``Transform`` keeps its rotation as a unit quaternion of its own and composes, inverts and turns it
with scalar arithmetic that follows scipy's ``Rotation`` step for step (the same products, sums
and normalisation, in the same order), so a chain of transforms gives the quaternions, matrices
and translations ``Rotation``'s operators give, to the last bit. The ``Rotation`` object is built
from the quaternion's source only when asked for (``Transform.rotation``): the per-frame path
(composition, inversion, the pose solver's left turns) then needs no ``Rotation`` at all.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError, FicapError

__all__ = ["Transform", "CAM_FROM_FORWARD", "rotate_covariance", "rotate_twist", "compose", "inverse",
           "from_rotvec", "real_numbers", "unit_quaternion", "UNIT_NORM_TOLERANCE"]

#: How far from unit length a quaternion from a file or a parameter may be (the rounding of a
#: hand-edited file); it is then normalised. Farther is a typo, refused.
UNIT_NORM_TOLERANCE = 1e-3

#: A quaternion (x, y, z, w) as four Python floats.
Quat = tuple[float, float, float, float]

#: Below this rotation angle (rad) a rotation vector's quaternion uses the Taylor series of
#: sin(angle / 2) / angle, as ``Rotation.from_rotvec`` does.
_SMALL_ANGLE_RAD = 1e-3


def real_numbers(values: Any, count: int, name: str,
                 error: type[FicapError] = ConfigError) -> np.ndarray:
    """``count`` finite real numbers from a file or a parameter (float64), or ``error`` naming
    ``name``: booleans and text are not numbers here (YAML's ``true`` is no 1, ``"1"`` no 1)."""
    items = list(values) if isinstance(values, (list, tuple, np.ndarray)) else None
    if items is None or len(items) != count or not all(
            isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
            for v in items):
        raise error(f"{name} must be {count} numbers, got {str(values)[:60]}")
    try:
        out = np.array([float(v) for v in items], dtype=np.float64)
    except OverflowError:
        raise error(f"{name} holds a number too large for a float") from None
    if not np.all(np.isfinite(out)):
        raise error(f"{name} must be finite numbers, got {str(values)[:60]}")
    return out


def unit_quaternion(values: Any, name: str, order: str = "wxyz",
                    error: type[FicapError] = ConfigError) -> Rotation:
    """A rotation from a quaternion in a file or a parameter: 4 finite real numbers in ``order``
    (``wxyz`` or ``xyzw``) of unit length to within ``UNIT_NORM_TOLERANCE``, then normalised.

    Raises:
        error: naming ``name``: not 4 finite numbers, or not of unit length (its norm, computed
            without overflow).
    """
    q = real_numbers(values, 4, name, error)
    scale = float(np.max(np.abs(q)))
    norm = scale * float(np.linalg.norm(q / scale)) if scale > 0 else 0.0
    if not abs(norm - 1.0) <= UNIT_NORM_TOLERANCE:
        raise error(f"{name} must be of unit length, its norm is {norm:.6g}")
    xyzw = q[[1, 2, 3, 0]] if order == "wxyz" else q
    return Rotation.from_quat(xyzw / norm)


def compose(a: Rotation, b: Rotation) -> Rotation:
    """``a * b``: apply b, then a."""
    return a * b


def inverse(a: Rotation) -> Rotation:
    """``a.inv()``."""
    return a.inv()


def from_rotvec(rotvec_rad: np.ndarray) -> Rotation:
    """``Rotation.from_rotvec`` of a rotation vector (3,), rad."""
    return Rotation.from_rotvec(np.asarray(rotvec_rad, dtype=np.float64))


# -- quaternion arithmetic (x, y, z, w), as scipy's Rotation does it --------------------------------


def _product(p: Quat, q: Quat) -> Quat:
    """The Hamilton product p q (apply q, then p), before normalisation."""
    px, py, pz, pw = p
    qx, qy, qz, qw = q
    return (pw * qx + qw * px + (py * qz - pz * qy),
            pw * qy + qw * py + (pz * qx - px * qz),
            pw * qz + qw * pz + (px * qy - py * qx),
            pw * qw - px * qx - py * qy - pz * qz)


def _normalised(q: Quat) -> Quat:
    x, y, z, w = q
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if norm == 0.0:
        raise ValueError("zero-norm quaternion")
    return (x / norm, y / norm, z / norm, w / norm)


def _conjugate(q: Quat) -> Quat:
    x, y, z, w = q
    return (-x, -y, -z, w)


def _rotvec_quat(rotvec_rad: Sequence[float]) -> Quat:
    """The unit quaternion of a rotation vector (rad), as ``Rotation.from_rotvec`` computes it."""
    x, y, z = (float(v) for v in rotvec_rad)
    angle = math.sqrt(x * x + y * y + z * z)
    if angle <= _SMALL_ANGLE_RAD:
        angle2 = angle * angle
        scale = 0.5 - angle2 / 48 + angle2 * angle2 / 3840
    else:
        scale = math.sin(angle / 2) / angle
    return (scale * x, scale * y, scale * z, math.cos(angle / 2))


def _rotvec(q: Quat) -> np.ndarray:
    """The rotation vector (3,), rad, angle in [0, pi], of a unit quaternion, as
    ``Rotation.as_rotvec`` computes it (from the canonical quaternion, w >= 0)."""
    x, y, z, w = _canonical(q)
    angle = 2 * math.atan2(math.sqrt(x * x + y * y + z * z), w)
    if angle <= _SMALL_ANGLE_RAD:
        angle2 = angle * angle
        scale = 2 + angle2 / 12 + 7 * angle2 * angle2 / 2880
    else:
        scale = angle / math.sin(angle / 2)
    return np.array([scale * x, scale * y, scale * z])


def _matrix(q: Quat) -> np.ndarray:
    """The rotation matrix (3, 3) of a unit quaternion."""
    x, y, z, w = q
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array([[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
                     [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
                     [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]])


def _canonical(q: Quat) -> Quat:
    """The quaternion of the same rotation with w >= 0 (the first non-zero component positive
    when w is 0), as ``Rotation.as_quat(canonical=True)``."""
    x, y, z, w = q
    if w < 0 or (w == 0 and (x < 0 or (x == 0 and (y < 0 or (y == 0 and z < 0))))):
        return (x * -1.0, y * -1.0, z * -1.0, w * -1.0)
    return q


# How a transform's ``Rotation`` is built when asked for: the public constructor that gives exactly
# its quaternion. ("quat", raw): ``Rotation.from_quat(raw)`` (a product before normalisation);
# ("rotvec", v): ``Rotation.from_rotvec(v)``; ("inv", r): ``r.inv()``.
_Source = tuple[str, Any]


def _build(source: _Source) -> Rotation:
    kind, value = source
    if kind == "quat":
        return Rotation.from_quat(np.array(value))
    if kind == "rotvec":
        return Rotation.from_rotvec(np.array(value))
    return value.inv()


def _source_of_inverse(source: _Source) -> _Source:
    kind, value = source
    if kind == "quat":  # normalising is symmetric in the signs
        return ("quat", _conjugate(value))
    if kind == "rotvec":
        return ("rotvec", tuple(-v for v in value))
    raise ValueError(f"no inverse source for {kind!r}")


class Transform:
    """A rigid transform ``T_a_b``: a rotation and a translation in metres. Immutable.

    Build one from a ``Rotation`` (``Transform(rotation, translation_m)``) or with the
    constructors below; ``rotation`` gives it back as a ``Rotation``.
    """

    __slots__ = ("_q", "_source", "_rotation", "_t", "_rotation_matrix")

    def __init__(self, rotation: Rotation, translation_m: Any) -> None:
        q = np.asarray(rotation.as_quat(), dtype=np.float64)
        if q.shape != (4,):
            raise ValueError(f"a Transform holds one rotation, got quaternions of shape {q.shape}")
        self._init(tuple(q.tolist()), None, rotation, translation_m)

    def _init(self, q: Quat, source: _Source | None, rotation: Rotation | None, translation_m: Any,
              rotation_matrix: np.ndarray | None = None) -> None:
        """``q``: the unit quaternion (x, y, z, w); ``source``: how to build its ``Rotation``
        (None: ``rotation`` is given); ``rotation_matrix``: its matrix when already computed."""
        t = np.array(translation_m, dtype=np.float64).reshape(3)
        t.setflags(write=False)
        if rotation_matrix is not None:
            rotation_matrix.setflags(write=False)
        set_ = object.__setattr__
        set_(self, "_q", q)
        set_(self, "_source", source)
        set_(self, "_rotation", rotation)
        set_(self, "_t", t)
        set_(self, "_rotation_matrix", rotation_matrix)

    @classmethod
    def _of(cls, q: Quat, source: _Source | None, rotation: Rotation | None, translation_m: Any,
            rotation_matrix: np.ndarray | None = None) -> Transform:
        out = cls.__new__(cls)
        out._init(q, source, rotation, translation_m, rotation_matrix)
        return out

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("Transform is immutable")

    def __reduce__(self) -> tuple[Any, ...]:
        return (Transform._of, (self._q, self._source, self._rotation, self._t))

    def __repr__(self) -> str:
        return f"Transform(q_xyzw={list(self._q)}, translation_m={self._t.tolist()})"

    # -- constructors -----------------------------------------------------------------------------

    @classmethod
    def identity(cls) -> Transform:
        one: Quat = (0.0, 0.0, 0.0, 1.0)
        return cls._of(one, ("quat", one), None, np.zeros(3))

    @classmethod
    def from_rvec_tvec(cls, rvec: np.ndarray, tvec_m: np.ndarray) -> Transform:
        """From OpenCV's rotation vector (rad) and translation (m)."""
        rv = tuple(np.asarray(rvec, dtype=np.float64).reshape(3).tolist())
        return cls._of(_rotvec_quat(rv), ("rotvec", rv), None, tvec_m)

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
        try:
            v = real_numbers(list(np.asarray(values).reshape(-1)), 7, name)
        except ConfigError:
            raise ConfigError(f"{name} must be 7 finite numbers: x y z (m) qx qy qz qw") from None
        return cls(unit_quaternion(v[3:], f"{name} quaternion (qx qy qz qw)", "xyzw"), v[:3])

    # -- views ------------------------------------------------------------------------------------

    @property
    def rotation(self) -> Rotation:
        """R_a_b as a ``Rotation`` (built on first use; its quaternion is this transform's)."""
        if self._rotation is None:
            object.__setattr__(self, "_rotation", _build(self._source))
        return self._rotation

    @property
    def translation_m(self) -> np.ndarray:
        """t_a_b (3,), m (read-only)."""
        return self._t

    @property
    def rotation_matrix(self) -> np.ndarray:
        """3x3 rotation matrix R_a_b (read-only; computed once)."""
        if self._rotation_matrix is None:
            m = _matrix(self._q)
            m.setflags(write=False)
            object.__setattr__(self, "_rotation_matrix", m)
        return self._rotation_matrix

    @property
    def matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix, translation in metres."""
        m = np.eye(4)
        m[:3, :3] = self.rotation_matrix
        m[:3, 3] = self._t
        return m

    @property
    def rvec(self) -> np.ndarray:
        """OpenCV rotation vector, rad, angle in [0, pi] (``rotation.as_rotvec()``)."""
        return _rotvec(self._q)

    @property
    def q_wxyz(self) -> np.ndarray:
        """Unit quaternion (w, x, y, z), w >= 0."""
        x, y, z, w = _canonical(self._q)
        return np.array([w, x, y, z])

    @property
    def q_xyzw(self) -> np.ndarray:
        """Unit quaternion (x, y, z, w), w >= 0 (scipy's and ROS message field order)."""
        return np.array(_canonical(self._q))

    # -- algebra ----------------------------------------------------------------------------------

    def __mul__(self, other: Transform) -> Transform:
        """Compose: ``T_a_b * T_b_c = T_a_c``."""
        if not isinstance(other, Transform):
            return NotImplemented
        raw = _product(self._q, other._q)
        t = self.rotation_matrix @ other._t + self._t
        return Transform._of(_normalised(raw), ("quat", raw), None, t)

    def inv(self) -> Transform:
        """``T_b_a``."""
        q = _conjugate(self._q)
        R = _matrix(q)
        source, rotation = self._inverse_source()
        return Transform._of(q, source, rotation, -(R @ self._t), R)

    def _inverse_source(self) -> tuple[_Source | None, Rotation | None]:
        """(source, rotation) of the inverse's ``Rotation``: the inverse of a given rotation is its
        ``inv()``, the inverse of such an inverse that rotation itself, and a built one's source
        is conjugated."""
        if self._source is None:
            return ("inv", self._rotation), None
        if self._source[0] == "inv":
            return None, self._source[1]
        return _source_of_inverse(self._source), None

    def turned(self, rotvec_rad: np.ndarray, translation_m: Any) -> Transform:
        """``(exp(rotvec) R_a_b, translation_m)``: the rotation turned by a rotation vector (rad,
        frame a's axes) after R_a_b, as ``Rotation.from_rotvec(rotvec) * rotation``, with a new
        translation (m). A left perturbation: the pose solver's step."""
        raw = _product(_rotvec_quat(np.asarray(rotvec_rad, dtype=np.float64).tolist()), self._q)
        return Transform._of(_normalised(raw), ("quat", raw), None, translation_m)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points (..., 3) from frame b into frame a (same length unit as the translation)."""
        pts = np.asarray(points, dtype=np.float64)
        return (pts.reshape(-1, 3) @ self.rotation_matrix.T + self._t).reshape(pts.shape)


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


def rotate_twist(twist: np.ndarray, rotation: Rotation) -> np.ndarray:
    """A (6,) twist (ROS order: linear, then angular velocity, in the parent frame's axes)
    re-expressed in a parent frame rotated by ``rotation`` (R_new_old): both vectors turn with the
    axes (a fixed frame's rotation adds no motion: what a static mount does)."""
    v = np.asarray(twist, dtype=np.float64).reshape(6)
    return np.concatenate([rotation.apply(v[:3]), rotation.apply(v[3:])])
