"""The 95 % error bounds of a pose under its covariance (ficap_ros.vision.error_bounds): the
quantile against Monte Carlo, a measured offset as a mean, the predictive bound of an estimated
variance, and the quantile table from scipy.special without scipy.stats."""

from __future__ import annotations

import numpy as np
import pytest

from ficap_ros.vision.error_bounds import error_bound95


def test_bound_quantile_matches_monte_carlo() -> None:
    rng = np.random.default_rng(1)
    for lam in ([1.0, 1.0, 1.0], [1.0, 0.05, 0.01], [2.0, 1.0, 0.0]):
        cov = np.zeros((6, 6))
        cov[3:, 3:] = np.diag(np.radians(1.0) ** 2 * np.array(lam))
        cov[:3, :3] = np.diag(1e-6 * np.array(lam))
        z = rng.standard_normal((200_000, 3)) * np.sqrt(lam)
        want = np.quantile(np.linalg.norm(z, axis=1), 0.95)
        rot, trans = error_bound95(cov)
        assert rot == pytest.approx(want, rel=0.03) and trans == pytest.approx(want, rel=0.03)


def test_bound_with_a_measured_offset() -> None:
    """A measured offset m is a mean, not a spread: the bound is the 95 % quantile of |m + e|
    (e ~ N(0, S), the covariance holding S + m m^T), within 2 % of Monte Carlo, and tighter than
    the Gaussian quantile of the same second moment when m dominates."""
    rng = np.random.default_rng(5)
    for lam, m in (([1.0, 0.3, 0.1], [0.0, 0.0, 3.0]), ([1.0, 0.3, 0.1], [3.0, 0.0, 0.0]),
                   ([0.01, 0.01, 1.0], [1.0, 0.0, 0.0]), ([1.0, 1.0, 1.0], [0.5, 0.5, 0.0])):
        lam, m = np.array(lam), np.array(m)
        second = np.diag(lam) + np.outer(m, m)
        cov = np.zeros((6, 6))
        cov[3:, 3:] = np.radians(1.0) ** 2 * second
        cov[:3, :3] = 1e-6 * second
        offset = np.concatenate([1e-3 * m, np.radians(1.0) * m])
        z = m + rng.standard_normal((200_000, 3)) * np.sqrt(lam)
        want = np.quantile(np.linalg.norm(z, axis=1), 0.95)
        rot, trans = error_bound95(cov, offset)
        assert rot == pytest.approx(want, rel=0.02) and trans == pytest.approx(want, rel=0.02)
        assert rot <= error_bound95(cov)[0] + 1e-9


def test_bound_predictive_for_an_estimated_variance() -> None:
    """A variance known to nu degrees of freedom (s^2 ~ sigma^2 chi2(nu) / nu): the predictive
    bound covers 95 % of fresh errors (the Gaussian quantile of s^2 covers fewer), with or without
    a measured offset beside it."""
    rng = np.random.default_rng(6)
    for lam, m, nu in (([1.0, 1.0, 1.0], [0.0, 0.0, 0.0], 6.0), ([1.0, 0.3, 0.1], [0.0, 0.0, 2.0], 8.0)):
        lam, m = np.array(lam), np.array(m)
        offset = np.concatenate([1e-3 * m, np.radians(1.0) * m])
        cover, cover_known = [], []
        for _ in range(6000):
            s2 = rng.chisquare(nu) / nu
            second = np.diag(lam) * s2 + np.outer(m, m)
            cov = np.zeros((6, 6))
            cov[3:, 3:] = np.radians(1.0) ** 2 * second
            cov[:3, :3] = 1e-6 * second
            e = np.linalg.norm(m + rng.standard_normal(3) * np.sqrt(lam))
            cover.append(e <= error_bound95(cov, offset, (nu, nu))[0])
            cover_known.append(e <= error_bound95(cov, offset)[0])
        assert 0.94 <= np.mean(cover) <= 0.965
        assert np.mean(cover_known) < np.mean(cover)


def test_quantile_tables_without_scipy_stats() -> None:
    """The bounds' quantile table (its chi column and its F columns) is scipy.stats' own
    (chi2.ppf, f.ppf) taken from scipy.special, bit for bit: importing scipy.stats is a large
    start-up cost of every command, and the pose modules (every replay, stats, the node) must not
    bring it in."""
    import subprocess
    import sys

    from scipy.stats import chi2, f

    from ficap_ros.vision import error_bounds

    nu = np.exp(error_bounds._F_LOG_NU)[:, None]
    dof = 1.0 / error_bounds._F_INV_DOF[None, 1:]
    assert np.array_equal(error_bounds._F_Q95[:, :1], chi2.ppf(0.95, nu) / nu)
    assert np.array_equal(error_bounds._F_Q95[:, 1:], f.ppf(0.95, nu, dof))
    run = subprocess.run([sys.executable, "-c", "import sys, ficap_ros.vision.pose, ficap_ros.tools.replay; "
                          "print('scipy.stats' in sys.modules)"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "False", "scipy.stats imported by ficap_ros.vision.pose / replay"
