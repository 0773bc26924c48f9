"""Quantiles and small summaries that skip NaN (frames without a pose carry NaN)."""

from __future__ import annotations

import numpy as np


def finite(x: object) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64).ravel()
    return a[np.isfinite(a)]


def q(x: object, pct: float) -> float:
    """The ``pct`` percentile of the finite values, NaN when there are none."""
    a = finite(x)
    return float(np.percentile(a, pct)) if a.size else float("nan")


def fmt(x: float, spec: str = ".3f") -> str:
    return "-" if not np.isfinite(x) else format(x, spec)


def med_p95(x: object, spec: str = ".3f") -> str:
    """``median / p95`` of the finite values."""
    return f"{fmt(q(x, 50), spec)} / {fmt(q(x, 95), spec)}"
