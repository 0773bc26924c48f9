"""ficap_ros.geometry.transform: Transform's own quaternion arithmetic gives Rotation's operators'
quaternions, matrices and translations bit for bit, and the transform algebra holds (hypothesis)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ficap_ros.errors import ConfigError
from ficap_ros.geometry.transform import (
    CAM_FROM_FORWARD,
    Transform,
    compose,
    from_rotvec,
    inverse,
    rotate_covariance,
    rotate_twist,
)


def _rotvecs(n: int, seed: int = 0) -> np.ndarray:
    """Rotation vectors of every size: tiny (a solver's last step), ordinary, near a half turn."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([10.0 ** rng.uniform(-12, -3, n // 3), rng.uniform(0, np.pi, n - n // 3)])
    return axes * angles[:, None]


# Rotation vectors: an axis and an angle from a solver's last step (1e-12 rad) to a half turn.
_axis = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda a: np.linalg.norm(a) > 1e-3)
_angle = st.one_of(st.floats(1e-12, 1e-3), st.floats(0.0, np.pi))
rotvecs = st.builds(lambda a, t: np.asarray(a) / np.linalg.norm(a) * t, _axis, _angle)
translations = st.tuples(*[st.floats(-10.0, 10.0)] * 3).map(np.array)


@st.composite
def transforms(draw: st.DrawFn) -> Transform:
    """Transforms as the package makes them: from a Rotation, from OpenCV's rvec, composed,
    inverted and turned (each keeps its own way of building its Rotation)."""
    kind = draw(st.sampled_from(["rotation", "rvec", "product", "inverse", "turned"]))
    rv, t = draw(rotvecs), draw(translations)
    if kind == "rotation":
        return Transform(Rotation.from_rotvec(rv), t)
    if kind == "rvec":
        return Transform.from_rvec_tvec(rv, t)
    other = Transform(Rotation.from_rotvec(draw(rotvecs)), draw(translations))
    if kind == "product":
        return Transform.from_rvec_tvec(rv, t) * other
    if kind == "inverse":
        return other.inv()
    return other.turned(rv, t)


def _same(a: Transform, b: Transform) -> bool:
    """Bit for bit: quaternion, matrix, translation and the Rotation."""
    return (np.array_equal(a.q_xyzw, b.q_xyzw) and np.array_equal(a.translation_m, b.translation_m)
            and np.array_equal(a.rotation_matrix, b.rotation_matrix)
            and np.array_equal(a.rotation.as_quat(), b.rotation.as_quat()))


def _close(a: Transform, b: Transform, atol: float = 1e-9) -> None:
    np.testing.assert_allclose(a.rotation_matrix, b.rotation_matrix, atol=atol)
    np.testing.assert_allclose(a.translation_m, b.translation_m, atol=atol)


# -- bit for bit against Rotation's operators -----------------------------------------------------------


def test_helpers_equal_the_operators_bit_for_bit() -> None:
    rv = _rotvecs(600)
    for v1, v2 in zip(rv[:300], rv[300:]):
        a, b = Rotation.from_rotvec(v1), Rotation.from_rotvec(v2)
        assert np.array_equal(from_rotvec(v1).as_quat(), a.as_quat())
        assert np.array_equal(compose(a, b).as_quat(), (a * b).as_quat())
        assert np.array_equal(compose(from_rotvec(v1), b).as_quat(canonical=True),
                              (a * b).as_quat(canonical=True))
        assert np.array_equal(inverse(a).as_quat(), a.inv().as_quat())


def test_transform_products_equal_rotation_arithmetic() -> None:
    rng = np.random.default_rng(1)
    rv = _rotvecs(40, seed=2)
    for v1, v2 in zip(rv[:20], rv[20:]):
        t1, t2 = rng.normal(size=3), rng.normal(size=3)
        A, B = Transform(Rotation.from_rotvec(v1), t1), Transform(Rotation.from_rotvec(v2), t2)
        AB = A * B
        assert np.array_equal(AB.rotation.as_quat(), (A.rotation * B.rotation).as_quat())
        assert np.array_equal(AB.translation_m, A.rotation.apply(t2) + t1)
        Ai = A.inv()
        assert np.array_equal(Ai.rotation.as_quat(), A.rotation.inv().as_quat())
        assert np.array_equal(Ai.translation_m, -A.rotation.inv().apply(t1))


@given(transforms(), transforms(), rotvecs, translations)
def test_algebra_equals_rotation_operators_bit_for_bit(A: Transform, B: Transform, rv: np.ndarray,
                                                       t: np.ndarray) -> None:
    """Composition, inversion and turning give the quaternion (as stored and canonical), matrix
    and translation Rotation's operators give, however the operands were built; chains too.
    (``Rotation.apply`` refuses read-only arrays: the translations are copied for it.)"""
    RA, RB = A.rotation, B.rotation
    AB = A * B
    assert np.array_equal(AB.rotation.as_quat(), (RA * RB).as_quat())
    assert np.array_equal(AB.q_xyzw, (RA * RB).as_quat(canonical=True))
    assert np.array_equal(AB.rotation_matrix, (RA * RB).as_matrix())
    assert np.array_equal(AB.translation_m, RA.apply(np.array(B.translation_m)) + A.translation_m)
    Ai = A.inv()
    assert np.array_equal(Ai.rotation.as_quat(), RA.inv().as_quat())
    assert np.array_equal(Ai.q_xyzw, RA.inv().as_quat(canonical=True))
    assert np.array_equal(Ai.translation_m, -RA.inv().apply(np.array(A.translation_m)))
    assert np.array_equal(Ai.inv().rotation.as_quat(), RA.inv().inv().as_quat())
    turned = A.turned(rv, t)
    assert np.array_equal(turned.rotation.as_quat(), (Rotation.from_rotvec(rv) * RA).as_quat())
    assert np.array_equal(AB.rvec, (RA * RB).as_rotvec()) and np.array_equal(Ai.rvec, RA.inv().as_rotvec())
    assert np.array_equal(turned.translation_m, t)
    chain = (AB.inv() * A).turned(rv, t).inv()
    ref = (Rotation.from_rotvec(rv) * ((RA * RB).inv() * RA)).inv()
    assert np.array_equal(chain.rotation.as_quat(), ref.as_quat())
    assert np.array_equal(chain.rotation_matrix, ref.as_matrix())


@given(rotvecs, translations)
def test_constructors_equal_rotation_constructors(rv: np.ndarray, t: np.ndarray) -> None:
    T = Transform.from_rvec_tvec(rv, t)
    R = Rotation.from_rotvec(rv)
    assert np.array_equal(T.rotation.as_quat(), R.as_quat())
    assert np.array_equal(T.q_xyzw, R.as_quat(canonical=True))
    assert np.array_equal(T.rotation_matrix, R.as_matrix())
    assert np.array_equal(T.rvec, R.as_rotvec())
    assert np.array_equal(T.translation_m, t)
    given_rotation = Transform(R, t)
    assert given_rotation.rotation is R
    assert _same(given_rotation, T)


# -- the algebra ----------------------------------------------------------------------------------


@given(transforms(), transforms(), transforms())
def test_composition_is_associative(A: Transform, B: Transform, C: Transform) -> None:
    _close((A * B) * C, A * (B * C), atol=1e-9)


@given(transforms())
def test_identity_and_inverse(T: Transform) -> None:
    one = Transform.identity()
    _close(T * one, T, atol=1e-12)
    _close(one * T, T, atol=1e-12)
    _close(T * T.inv(), one, atol=1e-11)
    _close(T.inv() * T, one, atol=1e-11)
    _close(T.inv().inv(), T, atol=1e-11)
    assert np.array_equal(T.inv().inv().q_xyzw, T.q_xyzw)  # conjugation is exact


@given(transforms(), transforms(), st.lists(translations, min_size=1, max_size=5).map(np.array))
def test_apply_is_the_homogeneous_matrix(A: Transform, B: Transform, points: np.ndarray) -> None:
    homogeneous = np.c_[points, np.ones(len(points))]
    np.testing.assert_allclose(A.apply(points), (homogeneous @ A.matrix.T)[:, :3], atol=1e-9)
    np.testing.assert_allclose((A * B).apply(points), A.apply(B.apply(points)), atol=1e-9)
    np.testing.assert_allclose(A.inv().apply(A.apply(points)), points, atol=1e-9)
    np.testing.assert_allclose((A * B).matrix, A.matrix @ B.matrix, atol=1e-9)
    assert A.apply(points[0]).shape == (3,)
    np.testing.assert_allclose(A.rotation_matrix @ A.rotation_matrix.T, np.eye(3), atol=1e-12)


@given(transforms())
def test_quaternion_orders_round_trip(T: Transform) -> None:
    """w-first and x-first are the same unit quaternion, w >= 0, and scipy reads each back in its
    own order (``scalar_first=True`` for w-first)."""
    q_wxyz, q_xyzw = T.q_wxyz, T.q_xyzw
    assert np.array_equal(q_wxyz, np.roll(q_xyzw, 1))
    assert q_wxyz[0] >= 0.0 and abs(np.linalg.norm(q_wxyz) - 1.0) < 1e-12
    for R in (Rotation.from_quat(q_wxyz, scalar_first=True), Rotation.from_quat(q_xyzw)):
        np.testing.assert_allclose(R.as_matrix(), T.rotation_matrix, atol=1e-12)
    np.testing.assert_allclose(T.rotation.as_quat(canonical=True, scalar_first=True), q_wxyz, atol=1e-15)
    back = Transform.from_xyz_q_xyzw(np.r_[T.translation_m, q_xyzw])
    _close(back, T, atol=1e-12)


@given(transforms())
def test_pickle_round_trip_is_exact(T: Transform) -> None:
    """A pickled transform (fleet workers send poses between processes) comes back bit for bit,
    its Rotation included, whether or not that was built before pickling."""
    fresh = pickle.loads(pickle.dumps(T))
    assert _same(fresh, T)
    T.rotation  # noqa: B018 - build it, then pickle again
    assert _same(pickle.loads(pickle.dumps(T)), T)
    assert _same(pickle.loads(pickle.dumps(T.inv())).inv(), T.inv().inv())


def test_transform_is_immutable() -> None:
    T = Transform.from_rvec_tvec([0.1, 0.2, 0.3], [1.0, 2.0, 3.0])
    with pytest.raises(AttributeError):
        T.translation_m = np.zeros(3)  # type: ignore[misc]
    with pytest.raises(ValueError):
        T.translation_m[0] = 5.0
    with pytest.raises(ValueError):
        T.rotation_matrix[0, 0] = 5.0
    with pytest.raises(ValueError, match="one rotation"):
        Transform(Rotation.from_rotvec(_rotvecs(3)), np.zeros(3))


def test_helper_rotations_behave_as_rotations() -> None:
    a, b = Rotation.from_rotvec([0.1, 0.2, 0.3]), Rotation.from_rotvec([0.3, -0.1, 0.2])
    c = compose(a, b)
    assert c.single and c.as_quat().shape == (4,) and len(Rotation.concatenate([c, a])) == 2
    assert np.array_equal(pickle.loads(pickle.dumps(c)).as_quat(), c.as_quat())
    stack = Rotation.from_rotvec(_rotvecs(6))
    assert np.array_equal(compose(stack, a).as_quat(), (stack * a).as_quat())
    assert np.array_equal(inverse(stack).as_quat(), stack.inv().as_quat())
    np.testing.assert_allclose(compose(c, inverse(c)).magnitude(), 0.0, atol=1e-15)


def test_from_xyz_q_xyzw_checks_its_numbers() -> None:
    T = Transform.from_xyz_q_xyzw([1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0 + 5e-4])
    np.testing.assert_allclose(T.q_xyzw, [0.0, 0.0, 0.0, 1.0])
    with pytest.raises(ConfigError, match="7 finite"):
        Transform.from_xyz_q_xyzw([1.0, 2.0, 3.0])
    with pytest.raises(ConfigError, match="unit length"):
        Transform.from_xyz_q_xyzw([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0])


def test_cam_from_forward_and_rotated_covariance() -> None:
    """The forward body axis (x) looks along the optical axis (z), left (y) is the image's -x, up
    (z) its -y; a rotated covariance keeps its total and moves variance with the axes."""
    np.testing.assert_allclose(CAM_FROM_FORWARD.apply([1.0, 0.0, 0.0]), [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(CAM_FROM_FORWARD.apply([0.0, 1.0, 0.0]), [-1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(CAM_FROM_FORWARD.apply([0.0, 0.0, 1.0]), [0.0, -1.0, 0.0], atol=1e-15)
    cov = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    turned = rotate_covariance(cov, Rotation.from_euler("z", 90, degrees=True))
    np.testing.assert_allclose(np.diag(turned), [2.0, 1.0, 3.0, 5.0, 4.0, 6.0], atol=1e-12)
    assert np.trace(turned) == pytest.approx(np.trace(cov))


def test_transform_algebra() -> None:
    a = Transform(Rotation.from_euler("z", 30, degrees=True), [1, 2, 3])
    b = Transform(Rotation.from_euler("x", -20, degrees=True), [0.5, 0, -1])
    p = np.array([0.3, -0.2, 0.9])
    np.testing.assert_allclose((a * b).apply(p), a.apply(b.apply(p)))
    np.testing.assert_allclose((a * a.inv()).matrix, np.eye(4), atol=1e-12)
    w, x, y, z = a.q_wxyz
    np.testing.assert_allclose(a.q_xyzw, [x, y, z, w])
    # The forward body frame's x is the optical axis, its z is the camera's -y (up).
    np.testing.assert_allclose(CAM_FROM_FORWARD.apply([1, 0, 0]), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(CAM_FROM_FORWARD.apply([0, 0, 1]), [0, -1, 0], atol=1e-12)


def test_quaternions_from_files_are_unit_real_numbers() -> None:
    """Four finite real numbers (YAML's true is no 1) of unit length within the rounding of a
    hand-edited file; their norm is computed without overflow (1e308 is not infinity's NaN)."""
    from ficap_ros.errors import CalibrationError
    from ficap_ros.geometry.transform import unit_quaternion

    r = unit_quaternion([0.7071, 0.7071, 0.0, 0.0], "q")  # rounded: normalised
    assert abs(r.magnitude() - np.pi / 2) < 1e-3
    np.testing.assert_allclose(unit_quaternion([0, 0, 0, 1], "q", "xyzw").as_quat(), [0, 0, 0, 1])
    for bad, says in (([True, False, 0, 0], "must be 4 numbers"), ([1, 0, 0], "must be 4 numbers"),
                      (["1", 0, 0, 0], "must be 4 numbers"), ([np.nan, 0, 0, 1], "finite"),
                      ([1e308, 1e308, 0, 0], r"norm is 1.41421e\+308"), ([0, 0, 0, 0], "norm is 0"),
                      ([1, 1, 0, 0], "norm is 1.41421")):
        with pytest.raises(CalibrationError, match=says):
            unit_quaternion(bad, "field q", "wxyz", CalibrationError)


@given(rotvec=rotvecs, a=rotvecs, lin=translations, t0=translations)
def test_a_rotated_twist_moves_points_as_the_rotated_frame_sees_them(rotvec, a, lin, t0) -> None:
    """``rotate_twist``: the velocity of a moving pose, seen from a frame turned and shifted by a
    fixed transform, is the twist with both vectors turned: the motion over a short step agrees
    to first order, and the covariance's rule (blockdiag(R, R)) holds."""
    R = Rotation.from_rotvec(rotvec)
    w = np.asarray(a) * 0.5
    twist = np.concatenate([lin, w])
    dt = 1e-6
    start = Transform(Rotation.from_rotvec(a), t0)
    step = Transform(Rotation.from_rotvec(w * dt) * start.rotation, t0 + np.asarray(lin) * dt)
    mount = Transform(R, np.array([0.3, -1.0, 2.0]))
    seen_start, seen_step = mount * start, mount * step
    turned = rotate_twist(twist, R)
    np.testing.assert_allclose((seen_step.translation_m - seen_start.translation_m) / dt,
                               turned[:3], atol=1e-6 * (1 + np.abs(turned[:3]).max()))
    spin = (seen_step.rotation * seen_start.rotation.inv()).as_rotvec() / dt
    np.testing.assert_allclose(spin, turned[3:], atol=1e-5 * (1 + np.abs(w).max()))
    B = np.kron(np.eye(2), R.as_matrix())
    np.testing.assert_allclose(turned, B @ twist, atol=1e-12 * (1 + np.abs(twist).max()))
