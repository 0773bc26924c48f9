"""Fitting covariance gains leave-one-set-out: each frame's covariance terms recorded once, the
bounds recomputed at any gains through the package's own functions, the gains of each set chosen
without it (several gains jointly, over a grid).

``record_terms`` records what ``uncertainty_terms`` returned for each pose a processor reports
(the terms and what the residuals showed, with the noise floor and mean of the frame's edge
shifts), so a gain of ``UncertaintyConfig`` can be changed after the run: ``combine_uncertainty``,
``uncertainty_bounds`` and ``error_bound95`` on the recorded terms give the bounds the pose would
have had with it (the pose itself does not depend on the gains). ``signed_offset_fit`` and
``shrunk_correction_ratios`` read the recorded signed common offset against the true errors.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from itertools import product

import numpy as np
from scipy.stats import binom

import ficap_ros.vision.motion as motion_module
import ficap_ros.vision.pose as pose_module
from ficap_ros.vision.error_bounds import error_bound95
from ficap_ros.vision.uncertainty import (
    UncertaintyConfig,
    combine_uncertainty,
    common_offset_mode,
    uncertainty_bounds,
)

#: The modules that call ``uncertainty_terms`` for a reported pose: the static fit's and the
#: rolling-shutter fit's (``motion.moving_pose``).
_CALLERS = (pose_module, motion_module)

#: The share of frames a set's translation bounds must cover for a gain to be chosen.
MIN_COVERAGE = 0.9


@dataclass(frozen=True)
class FrameTerms:
    """One pose's covariance terms (``uncertainty_terms``) and its true errors (the translation
    error also as a vector, camera axes, mm, when known), and the cap's true angular speed at
    the frame (deg/s, from the previous frame's truth; NaN without one within 0.1 s)."""

    terms: dict[str, np.ndarray]
    seen: dict[str, float]
    rot_err_deg: float
    trans_err_mm: float
    trans_error_mm: np.ndarray | None = None
    speed_dps: float = float("nan")


def light_gradient_floor_px(edge_shift_px: np.ndarray, centres_px: np.ndarray) -> float:
    """The spread ``light_gradient_px`` shows from the edge shifts' scatter alone, px: a plane fitted
    by least squares to n shifts scattering independently with variance s^2 about a plane has a
    fitted spread whose square exceeds the true plane's by 2 s^2 / n on average (the two slopes
    take two of the scatter's n degrees of freedom); s^2 is estimated from the plane's residuals
    (n - 3 degrees of freedom). 0 where ``light_gradient_px`` is 0 (fewer than six fitted tags)."""
    es = np.asarray(edge_shift_px, dtype=float)
    ok = np.isfinite(es)
    n = int(ok.sum())
    if n < 6:
        return 0.0
    c = np.asarray(centres_px, dtype=float)[ok]
    X = np.column_stack([np.ones(n), c - c.mean(axis=0)])
    coef, *_ = np.linalg.lstsq(X, es[ok], rcond=None)
    s2 = float(np.sum((es[ok] - X @ coef) ** 2)) / (n - 3)
    return float(np.sqrt(2.0 * s2 / n))


@contextmanager
def record_terms() -> Iterator[list[tuple[np.ndarray, dict, dict]]]:
    """Within the block, every ``uncertainty_terms`` call of ``ficap_ros.vision.pose`` and
    ``ficap_ros.vision.motion`` (a rolling shutter's pose) appends (the pose's translation, terms,
    seen) to the yielded list (``terms_of`` picks a pose's); the recorded ``seen`` also holds
    ``light_gradient_floor`` (``light_gradient_floor_px``, 0 when the call had no edge shifts)."""
    calls: list[tuple[np.ndarray, dict, dict]] = []
    original = pose_module.uncertainty_terms

    def recording(obs, T, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202 - as wrapped
        terms, seen = original(obs, T, *args, **kwargs)
        shifts = args[1] if len(args) > 1 else kwargs.get("edge_shift_px")
        floor = 0.0 if shifts is None else light_gradient_floor_px(shifts, obs.image_px.mean(axis=1))
        calls.append((np.array(T.translation_m), terms, {**seen, "light_gradient_floor": floor}))
        return terms, seen

    for module in _CALLERS:
        module.uncertainty_terms = recording
    try:
        yield calls
    finally:
        for module in _CALLERS:
            module.uncertainty_terms = original


def terms_of(calls: Sequence[tuple[np.ndarray, dict, dict]], translation_m: np.ndarray
             ) -> tuple[dict, dict] | None:
    """The terms of the reported pose: the last call whose pose is the reported one."""
    for t, terms, seen in reversed(calls):
        if np.array_equal(t, translation_m):
            return terms, seen
    return None


def bounds_at(frames: Sequence[FrameTerms], config: UncertaintyConfig) -> np.ndarray:
    """(frames, 2): each frame's (rotation deg, translation mm) 95 % bounds under ``config``."""
    out = np.empty((len(frames), 2))
    for i, f in enumerate(frames):
        cov = combine_uncertainty(f.terms, f.seen, config)
        out[i] = error_bound95(cov, *uncertainty_bounds(f.terms, f.seen, config, cov))
    return out


@dataclass(frozen=True)
class SetFit:
    """One held-out set: the gains fitted without it and its figures at those gains."""

    name: str
    gains: dict[str, float]
    frames: int
    rot_coverage: float
    rot_sharpness: float
    trans_coverage: float
    trans_sharpness: float
    trans_misses: int


def gain_grid(axes: dict[str, Sequence[float]], tied: dict[str, str] | None = None,
              fixed: dict[str, float] | None = None) -> list[dict[str, float]]:
    """Every combination of the gains' values (``UncertaintyConfig`` field -> the values to try),
    the last field varying fastest; ``tied`` fields (field -> the axis it equals) and ``fixed``
    ones (field -> value) added to every point."""
    points = [dict(zip(axes, map(float, values))) for values in product(*axes.values())]
    return [{**p, **{k: p[axis] for k, axis in (tied or {}).items()}, **(fixed or {})} for p in points]


def coverage_table(sets: dict[str, Sequence[FrameTerms]], base: UncertaintyConfig,
                   grid: Sequence[dict[str, float]]) -> dict[str, np.ndarray]:
    """Per set, (grid points, 5): rotation coverage, rotation sharpness, translation coverage,
    translation sharpness, translation misses with ``base``'s fields set to each grid point."""
    table = {}
    for name, frames in sets.items():
        er = np.array([f.rot_err_deg for f in frames])
        et = np.array([f.trans_err_mm for f in frames])
        rows = []
        for point in grid:
            b = bounds_at(frames, replace(base, **point))
            rows.append((np.mean(er <= b[:, 0]), np.median(b[:, 0]) / np.median(er),
                         np.mean(et <= b[:, 1]), np.median(b[:, 1]) / np.median(et),
                         int(np.sum(et > b[:, 1]))))
        table[name] = np.array(rows)
    return table


def fitted_index(table: dict[str, np.ndarray], train: Sequence[str], frames: dict[str, int]) -> int:
    """Index of the grid point fitted on the sets ``train`` (``frames``: each set's frame count):
    of those whose translation bounds cover at least ``MIN_COVERAGE`` of every training set's
    frames, the one with the smallest mean log translation sharpness over the training sets,
    each set weighted by its frames (ties: the first). Weighted so that every frame counts once:
    the worst set's sharpness, a median ratio of 12-25 frames, is too noisy to decide between
    gains that substitute for each other on the other sets. None covers: the point with the
    highest worst coverage."""
    rows = np.stack([table[s] for s in train])  # (sets, points, 5)
    coverage, sharpness = rows[:, :, 2], np.log(np.maximum(rows[:, :, 3], 1e-12))
    ok = np.all(coverage >= MIN_COVERAGE - 1e-9, axis=0)
    if not ok.any():
        return int(np.argmax(coverage.min(axis=0)))
    weights = np.array([frames[s] for s in train], dtype=float)
    score = np.where(ok, weights @ sharpness / weights.sum(), np.inf)
    return int(np.argmin(score))


def leave_one_set_out(table: dict[str, np.ndarray], grid: Sequence[dict[str, float]],
                      frames: dict[str, int]) -> list[SetFit]:
    """Each set's figures at the gains fitted on the other sets (``fitted_index``)."""
    fits = []
    for name, rows in table.items():
        i = fitted_index(table, [s for s in table if s != name], frames)
        r = rows[i]
        fits.append(SetFit(name, grid[i], frames[name], *map(float, r[:4]), int(r[4])))
    return fits


def binomial_reading(misses: int, frames: int, p_miss: float = 0.05) -> str:
    """How likely a calibrated 95 % bound misses this many frames or more (more than expected)
    or this many or fewer (fewer), and how likely 90-99 % coverage is at all for the set's size."""
    if misses > p_miss * frames:
        tail = f"P(>= {misses}) = {binom.sf(misses - 1, frames, p_miss):.2f}"
    else:
        tail = f"P(<= {misses}) = {binom.cdf(misses, frames, p_miss):.2f}"
    lo, hi = int(np.ceil(0.01 * frames - 1e-9)), int(np.floor(0.10 * frames + 1e-9))
    band = binom.cdf(hi, frames, p_miss) - binom.cdf(lo - 1, frames, p_miss) if hi >= lo else 0.0
    return f"{tail}; P(90-99 %) = {band:.2f}"


def offset_mode_mm(frame: FrameTerms) -> np.ndarray:
    """(3,) the translation (camera axes, mm) one px of outward common radial offset causes: the
    mode (``uncertainty.common_offset_mode``), oriented toward the camera
    (-z): every tag's corners moved outward is a larger image, a closer cap."""
    a = 1e3 * common_offset_mode(frame.terms)[:3]
    return a if a[2] <= 0.0 else -a


def signed_offset_fit(frames: Sequence[FrameTerms]) -> dict[str, float]:
    """How the signed common offset (``seen["bias_common_signed"]``) predicts the translation
    error along its mode (``offset_mode_mm``), over frames with a known error vector: Pearson
    correlation, least-squares slope of the error on the prediction (1: the offset as measured),
    the share of the error's square along the mode the prediction explains at slope 1
    (1 - sum (e - p)^2 / sum e^2: negative where correcting by it would add error), both means
    (mm), and the share of frames whose offset exceeds its standard error."""
    e, p, above = [], [], []
    for f in frames:
        if f.trans_error_mm is None:
            continue
        a = offset_mode_mm(f)
        norm = float(np.linalg.norm(a))
        if not norm > 0.0:
            continue
        off = f.seen.get("bias_common_signed", 0.0)
        e.append(float(f.trans_error_mm @ a) / norm)
        p.append(norm * off)
        above.append(abs(off) > f.seen.get("bias_common_se", 0.0))
    e, p = np.array(e), np.array(p)
    if e.size < 3 or not (np.std(e) > 0.0 and np.std(p) > 0.0):
        return {}
    return {"frames": float(e.size), "corr": float(np.corrcoef(e, p)[0, 1]), "slope": float(e @ p / (p @ p)),
            "explained": float(1.0 - np.sum((e - p) ** 2) / np.sum(e**2)), "mean_error": float(e.mean()),
            "mean_predicted": float(p.mean()), "above_se": float(np.mean(above))}


def shrunk_correction_ratios(frames: Sequence[FrameTerms], k: float) -> tuple[float, float]:
    """Median and p95 of the translation error length after subtracting, to first order, the
    pose error the signed common offset predicts shrunk by its standard error
    (offset * max(0, 1 - k se^2 / offset^2)), each over the uncorrected one's."""
    before, after = [], []
    for f in frames:
        if f.trans_error_mm is None:
            continue
        off = f.seen.get("bias_common_signed", 0.0)
        se = f.seen.get("bias_common_se", 0.0)
        shrunk = off * max(0.0, 1.0 - k * se * se / off**2) if off != 0.0 else 0.0
        before.append(float(np.linalg.norm(f.trans_error_mm)))
        after.append(float(np.linalg.norm(f.trans_error_mm - offset_mode_mm(f) * shrunk)))
    if not before:
        return float("nan"), float("nan")
    return (float(np.median(after) / np.median(before)),
            float(np.percentile(after, 95) / np.percentile(before, 95)))


def calibrated_target_odds(frames: Sequence[FrameTerms], config: UncertaintyConfig, seed: int = 0,
                           replicas: int = 4000, draws: int = 400) -> tuple[float, float]:
    """How likely a set of these frames meets the translation target at all, were each frame's
    bound exactly calibrated: errors drawn from each frame's covariance under ``config`` (its
    translation block, Gaussian), each frame's bound the 95 % quantile of its error length;
    over replicas of the whole set, the share with sharpness (median bound / median error) <= 3,
    and with that and coverage 90-99 % both. A depth-dominated (1-D) error's sharpness is 2.91
    for an infinite set, and a set's median scatters with its size."""
    rng = np.random.default_rng(seed)
    bounds, scales = [], []
    for f in frames:
        block = 1e6 * combine_uncertainty(f.terms, f.seen, config)[:3, :3]
        lam, vec = np.linalg.eigh(0.5 * (block + block.T))
        scale = vec * np.sqrt(np.clip(lam, 0.0, None))
        bounds.append(np.percentile(np.linalg.norm(rng.standard_normal((draws, 3)) @ scale.T, axis=1), 95))
        scales.append(scale)
    bounds = np.array(bounds)
    errors = np.stack([np.linalg.norm(rng.standard_normal((replicas, 3)) @ s.T, axis=1) for s in scales], axis=1)
    sharp = np.median(bounds) / np.median(errors, axis=1)
    cover = np.mean(errors <= bounds, axis=1)
    ok = sharp <= 3.0
    return float(np.mean(ok)), float(np.mean(ok & (cover >= 0.9) & (cover <= 0.99)))
