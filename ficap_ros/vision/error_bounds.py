"""The 95 % error bounds of a pose under its covariance: quantiles of the geodesic rotation angle
and of the translation length.

An error e ~ N(m, S) in three dimensions has a length whose square is a weighted sum of noncentral
chi-squares; ``error_bound95`` matches its mean and variance with a scaled chi-square
(Welch-Satterthwaite) and takes that distribution's 95 % quantile, exact for an isotropic error and
within a few percent of Monte Carlo for the anisotropic ones a pose has. When the covariance is
itself estimated (pooled from residuals with a known number of degrees of freedom), the bound is
the predictive one: the F quantile in place of the chi-square's. The covariance and what the bounds
need beyond it (the measured offset, the degrees of freedom) come from
``ficap_ros.vision.uncertainty``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["error_bound95"]


#: The 95 % quantile of F(nu, nu_e) over a grid of log(nu) (the error's effective dimensions: 1-3
#: for a zero-mean error, up to ~1e6 when a measured offset dominates) and 1 / nu_e (the degrees
#: of freedom its variance was estimated from; 0: known). F(nu, inf) = chi2(nu) / nu.
_F_LOG_NU = np.linspace(np.log(0.5), np.log(1e6), 90)
_F_INV_DOF = np.linspace(0.0, 0.5, 26)


def _f_quantile_table() -> np.ndarray:
    # scipy.stats' f.ppf(q, a, b) is fdtri(a, b, q) and chi2.ppf(q, nu) 2 * gammaincinv(nu / 2, q)
    # (bit-identical): not importing scipy.stats keeps its start-up cost off every command.
    from scipy.special import fdtri, gammaincinv

    nu = np.exp(_F_LOG_NU)[:, None]
    inv = _F_INV_DOF[None, :]
    with np.errstate(divide="ignore"):
        dof = np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), np.inf)
    return np.where(np.isinf(dof), 2.0 * gammaincinv(nu / 2, 0.95) / nu,
                    fdtri(nu, np.where(np.isinf(dof), 1.0, dof), 0.95))


_F_Q95 = _f_quantile_table()


#: ``_F_Q95`` and its grid as Python floats: ``_f_quantile95`` runs six times a pose, on scalars,
#: where Python's float arithmetic is cheaper than numpy's scalar indexing.
_F_Q95_ROWS = _F_Q95.tolist()
_F_X0, _F_DX = float(_F_LOG_NU[0]), float(_F_LOG_NU[1] - _F_LOG_NU[0])
_F_DY = float(_F_INV_DOF[1] - _F_INV_DOF[0])


def _f_quantile95(nu: float, dof: float) -> float:
    """Bilinear lookup of the 95 % quantile of F(nu, dof) (dof >= 2; inf: chi2(nu) / nu)."""
    x = (math.log(min(max(nu, 0.5), 1e6)) - _F_X0) / _F_DX
    y = min(1.0 / max(dof, 2.0), 0.5) / _F_DY
    i = min(int(x), len(_F_LOG_NU) - 2)
    j = min(int(y), len(_F_INV_DOF) - 2)
    fx, fy = x - i, y - j
    q0, q1 = _F_Q95_ROWS[i], _F_Q95_ROWS[i + 1]
    return float((q0[j] * (1 - fx) + q1[j] * fx) * (1 - fy) + (q0[j + 1] * (1 - fx) + q1[j + 1] * fx) * fy)


def _bound95(block: np.ndarray, offset: np.ndarray, dof: float) -> float:
    """95 % quantile of |m + e|, e ~ N(0, S) with ``block`` = S + m m^T: |m + e|^2 matched in mean
    and variance by a scaled chi-square (Welch-Satterthwaite; for m = 0 that of |e| itself).
    When S is known only to ``dof`` degrees of freedom, S is first widened to its predictive size
    (by the ratio of the F to the chi-square quantile of its own effective dimensions: for m = 0
    exactly the predictive F quantile); the offset is a measurement, not widened. The three
    eigenvalues as Python floats (sums in numpy's order for three: left to right)."""
    S = 0.5 * (block + block.T) - np.outer(offset, offset)
    lam = [max(v, 0.0) for v in np.linalg.eigvalsh(S).tolist()]
    total = sum(lam)
    if math.isfinite(dof) and total > 0.0:
        nu_s = total * total / sum(v * v for v in lam)
        widen = _f_quantile95(nu_s, dof) / _f_quantile95(nu_s, math.inf)
        lam = [v * widen for v in lam]
        S = S * widen
    mean = sum(lam) + float(offset @ offset)
    if mean <= 0.0:
        return 0.0
    var = 2.0 * sum(v * v for v in lam) + float(4.0 * offset @ S @ offset)
    nu = 2.0 * mean * mean / var if var > 1e-12 * mean * mean else 1e6
    return math.sqrt(mean * _f_quantile95(nu, math.inf))


def error_bound95(covariance: np.ndarray, offset: np.ndarray | None = None,
                  dof: tuple[float, float] = (float("inf"), float("inf"))) -> tuple[float, float]:
    """(rotation deg, translation mm): 95 % quantiles of the geodesic rotation error and of the
    translation error's length under the covariance (first order).

    Args:
        covariance: 6x6, ROS order: the error's second moment (``combine_uncertainty``).
        offset: (6,) the part of it that is a measured mean error (``uncertainty_bounds``):
            the covariance holds ``S + offset offset^T`` with ``S`` the random part. None: 0.
        dof: (rotation, translation) degrees of freedom the random part is known to; inf: known
            (Gaussian), finite: the predictive (F) quantile.
    """
    m = np.zeros(6) if offset is None else np.asarray(offset, dtype=float)
    out = []
    for rows, scale, nu_e in ((slice(3, 6), np.degrees(1.0), dof[0]), (slice(0, 3), 1e3, dof[1])):
        block = covariance[rows, rows]
        if not np.all(np.isfinite(block)):
            out.append(float("inf"))
            continue
        out.append(_bound95(block, m[rows], nu_e) * scale)
    return out[0], out[1]
