"""ficap_ros.geometry.transform: the rotation helpers give Rotation's own quaternions, bit for bit."""

from __future__ import annotations

import pickle

import numpy as np
from scipy.spatial.transform import Rotation

from ficap_ros.geometry import transform
from ficap_ros.geometry.transform import Transform, compose, from_rotvec, inverse


def _rotvecs(n: int, seed: int = 0) -> np.ndarray:
    """Rotation vectors of every size: tiny (a solver's last step), ordinary, near a half turn."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([10.0 ** rng.uniform(-12, -3, n // 3), rng.uniform(0, np.pi, n - n // 3)])
    return axes * angles[:, None]


def test_helpers_equal_the_operators_bit_for_bit() -> None:
    # The pinned scipy's kernels are the ones taken (else the helpers are the operators themselves).
    assert transform._FAST
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


def test_helper_rotations_behave_as_rotations() -> None:
    a, b = Rotation.from_rotvec([0.1, 0.2, 0.3]), Rotation.from_rotvec([0.3, -0.1, 0.2])
    c = compose(a, b)
    assert c.single and c.as_quat().shape == (4,) and len(Rotation.concatenate([c, a])) == 2
    assert np.array_equal(pickle.loads(pickle.dumps(c)).as_quat(), c.as_quat())
    # Stacks (and anything but single rotations) go through the operators.
    stack = Rotation.from_rotvec(_rotvecs(6))
    assert np.array_equal(compose(stack, a).as_quat(), (stack * a).as_quat())
    assert np.array_equal(inverse(stack).as_quat(), stack.inv().as_quat())
    np.testing.assert_allclose(compose(c, inverse(c)).magnitude(), 0.0, atol=1e-15)
