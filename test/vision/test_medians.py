"""Medians and quantiles of many samples at once, against numpy's own per sample: ``np.median`` and
``np.quantile`` (lower, nearest) with the empty-sample and NaN rules each function states."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from ficap_ros.vision.medians import (
    GroupLayout,
    group_median_nan_propagating,
    group_median_of_finite,
    group_nearest_quantile_of_finite,
    row_lower_median,
    row_median,
)

#: Grey levels (ties and halves) or continuous values, as the corner stage feeds them.
_values = st.one_of(st.integers(0, 255).map(float), st.floats(-1e6, 1e6, allow_nan=False, width=32))


@st.composite
def _rows(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray]:
    """(R, M) finite values and a mask (rows with no entry included)."""
    r, m = draw(st.integers(1, 6)), draw(st.integers(1, 12))
    x = np.array(draw(st.lists(_values, min_size=r * m, max_size=r * m))).reshape(r, m)
    mask = np.array(draw(st.lists(st.booleans(), min_size=r * m, max_size=r * m))).reshape(r, m)
    return x, mask


@st.composite
def _groups(draw: st.DrawFn, special: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(values (T,), mask (T,), counts (G,)): groups of 0-9 entries one after the other; with
    ``special``, NaN and infinite entries among them."""
    counts = np.array(draw(st.lists(st.integers(0, 9), min_size=1, max_size=6)))
    t = int(counts.sum())
    entry = st.one_of(_values, st.sampled_from([np.nan, np.inf, -np.inf])) if special else _values
    x = np.array(draw(st.lists(entry, min_size=t, max_size=t)), dtype=np.float64)
    mask = np.array(draw(st.lists(st.booleans(), min_size=t, max_size=t)), dtype=bool)
    return x, mask, counts


def _runs(x: np.ndarray, counts: np.ndarray) -> list[np.ndarray]:
    return np.split(x, np.cumsum(counts)[:-1])


@given(_rows())
def test_row_median_is_np_median_of_the_masked_entries(rows: tuple[np.ndarray, np.ndarray]) -> None:
    x, mask = rows
    got = row_median(x, mask)
    for k in range(len(x)):
        want = np.median(x[k][mask[k]]) if mask[k].any() else 0.0
        assert got[k] == want, (k, got[k], want)


@given(_rows())
def test_row_lower_median_is_the_lower_quantile_and_an_entry(rows: tuple[np.ndarray, np.ndarray]) -> None:
    x, mask = rows
    got = row_lower_median(x, mask)
    for k in range(len(x)):
        v = x[k][mask[k]]
        if len(v):
            assert got[k] == np.quantile(v, 0.5, method="lower") and got[k] in v
            assert got[k] <= np.median(v)
        else:
            assert got[k] == np.inf


@given(_groups(special=True))
def test_group_median_of_finite_leaves_out_nan_inf_and_masked(groups: tuple[np.ndarray, ...]) -> None:
    x, mask, counts = groups
    got = group_median_of_finite(x, mask, counts)
    for g, (v, m) in enumerate(zip(_runs(x, counts), _runs(mask, counts))):
        v = v[m & np.isfinite(v)]
        assert got[g] == (np.median(v) if len(v) else 0.0)


@given(_groups(special=True), st.sampled_from([0.0, 0.1, 0.25, 0.5, 0.9, 1.0]))
def test_group_nearest_quantile_of_finite_is_np_quantile_nearest(groups: tuple[np.ndarray, ...], q: float) -> None:
    x, mask, counts = groups
    got = group_nearest_quantile_of_finite(x, mask, counts, q)
    for g, (v, m) in enumerate(zip(_runs(x, counts), _runs(mask, counts))):
        v = v[m & np.isfinite(v)]
        assert got[g] == (np.quantile(v, q, method="nearest") if len(v) else 0.0)


@given(_groups(special=True), st.booleans())
def test_group_median_nan_propagating_is_np_median_bit_for_bit(groups: tuple[np.ndarray, ...], masked: bool) -> None:
    x, mask, counts = groups
    layout = GroupLayout.of_counts(counts)
    med, cnt = group_median_nan_propagating(x, layout, mask if masked else None)
    for g, (v, m) in enumerate(zip(_runs(x, counts), _runs(mask, counts))):
        v = v[m] if masked else v
        assert cnt[g] == len(v)
        want = np.median(v) if len(v) else 0.0
        assert (np.isnan(want) and np.isnan(med[g])) or med[g] == want, (g, med[g], want)


@given(st.lists(st.integers(0, 7), max_size=8))
def test_group_layout_places_each_entry_in_its_group(counts: list[int]) -> None:
    layout = GroupLayout.of_counts(np.array(counts, dtype=np.int64))
    assert layout.n == len(counts) and layout.width == max(counts, default=0)
    want = [(g, p) for g, c in enumerate(counts) for p in range(c)]
    assert list(zip(layout.group.tolist(), layout.pos.tolist())) == want


def test_group_median_is_np_median_per_group() -> None:
    """The photometric fit's all-tags-at-once median (levels, robust sd) equals np.median tag by
    tag, bit for bit: odd and even runs, masked entries, a run with nothing left, a NaN, empty
    groups at the end, integer grey levels (halves) and continuous residuals."""
    rng = np.random.default_rng(7)
    counts = np.array([1, 2, 7, 8, 1500, 1499, 3, 0, 0])
    n = len(counts)
    layout = GroupLayout.of_counts(counts)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    for x in (rng.integers(0, 256, len(layout.group)).astype(np.float64),
              rng.normal(0.0, 3.0, len(layout.group)) ** 2):
        x[starts[2] + 3] = np.nan  # group 2's median is NaN, as np.median's
        for mask in (None, x > np.nanmedian(x), np.zeros(len(x), dtype=bool)):
            med, cnt = group_median_nan_propagating(x, layout, mask)
            for g in range(n):
                run = x[starts[g]:starts[g] + counts[g]]
                if mask is not None:
                    run = run[mask[starts[g]:starts[g] + counts[g]]]
                assert cnt[g] == len(run)
                want = np.median(run) if len(run) else 0.0
                assert (np.isnan(want) and np.isnan(med[g])) or med[g] == want, (g, med[g], want)
