"""Medians and quantiles of many small samples at once: one sort for all of them, no Python loop.

Two layouts:

- rows: a (R, M) array and a (R, M) mask of the entries that count (``row_median``,
  ``row_lower_median``);
- groups: a flat (T,) array whose entries come group after group (group 0's, then group 1's, ...),
  ``counts`` (G,) entries each (``GroupLayout``). A group is copied into one row of a (G, width)
  array padded with +inf, which sorts to the row's end.

``np.median`` and ``np.nanmedian`` over a ragged set of samples need one call per sample (or NaN
padding, which ``np.nanmedian`` handles slowly); these take one sort. Each function says what it
returns for an empty sample and how it treats NaN and infinite entries.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

__all__ = ["GroupLayout", "row_median", "row_lower_median", "group_median_of_finite",
           "group_nearest_quantile_of_finite", "group_median_nan_propagating"]


@dataclass(frozen=True)
class GroupLayout:
    """Where each entry of a group-after-group array sits in the padded (n, width) array.

    Attributes:
        group: (T,) int, the group of each entry (0..n-1, non-decreasing).
        pos: (T,) int, its place within its group.
        n: number of groups.
        width: size of the largest group (0 without groups).
    """

    group: np.ndarray
    pos: np.ndarray
    n: int
    width: int

    @classmethod
    def of_counts(cls, counts: np.ndarray) -> GroupLayout:
        """The layout of groups of ``counts`` (G,) entries, laid out one after the other."""
        counts = np.asarray(counts, dtype=np.int64)
        group = np.repeat(np.arange(len(counts)), counts)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        pos = np.arange(int(counts.sum())) - starts[group]
        return cls(group, pos, len(counts), int(counts.max()) if len(counts) else 0)


@lru_cache(maxsize=64)
def _cached_layout(counts_key: bytes) -> GroupLayout:
    """``GroupLayout.of_counts`` of an int64 counts array given as its bytes, read-only and cached
    (the tags a tracked cap shows give the same groups frame after frame)."""
    layout = GroupLayout.of_counts(np.frombuffer(counts_key, dtype=np.int64))
    for a in (layout.group, layout.pos):
        a.setflags(write=False)
    return layout


def _layout(counts: np.ndarray) -> GroupLayout:
    return _cached_layout(np.ascontiguousarray(counts, dtype=np.int64).tobytes())


def _middle_of_sorted(srt: np.ndarray, cnt: np.ndarray) -> np.ndarray:
    """Median of the first ``cnt`` entries of each sorted row of ``srt`` (R, M): the middle entry,
    or the mean of the middle two as ``np.median`` computes it ((a + b) / 2); 0.0 where cnt is 0."""
    if srt.shape[1] == 0:
        return np.zeros(len(srt))
    rows = np.arange(len(srt))
    lo = srt[rows, np.maximum((cnt - 1) // 2, 0)]
    hi = srt[rows, np.maximum(cnt // 2, 0)]
    return np.where(cnt > 0, 0.5 * (lo + hi), 0.0)


def row_median(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(R,) ``np.median`` of each row's entries where ``mask`` ((R, M) both), 0.0 for a row
    with none.

    Entries where ``mask`` must not be NaN: a NaN counts toward the row's size but sorts last,
    which moves the middle (``np.median`` would return NaN).
    """
    srt = np.sort(np.where(mask, x, np.inf), axis=1)
    return _middle_of_sorted(srt, mask.sum(axis=1))


def row_lower_median(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(R,) lower median of each row's entries where ``mask`` ((R, M) both): the
    ((k - 1) // 2)-th smallest of its k entries, always an entry itself (``np.quantile(..., 0.5,
    method="lower")``); +inf for a row with none. Entries where ``mask`` must not be NaN."""
    count = mask.sum(axis=1)
    ordered = np.sort(np.where(mask, x, np.inf), axis=1)
    return ordered[np.arange(len(x)), np.maximum(count - 1, 0) // 2]


def _padded(x: np.ndarray, mask: np.ndarray, layout: GroupLayout) -> np.ndarray:
    """(n, width) the groups' entries where ``mask``, one group a row, +inf elsewhere."""
    pad = np.full((layout.n, layout.width), np.inf)
    pad[layout.group, layout.pos] = np.where(mask, x, np.inf)
    return pad


def group_median_of_finite(x: np.ndarray, mask: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(G,) ``np.median`` of each group's finite entries where ``mask`` (x and mask (T,), groups
    of ``counts`` (G,) entries one after the other); 0.0 for a group with none. NaN and infinite
    entries are left out, as masked ones are."""
    pad = _padded(x, mask, _layout(counts))
    return row_median(pad, np.isfinite(pad))


def group_nearest_quantile_of_finite(
    x: np.ndarray, mask: np.ndarray, counts: np.ndarray, q: float
) -> np.ndarray:
    """(G,) quantile ``q`` of each group's finite entries where ``mask``, by nearest rank
    (``np.quantile(..., q, method="nearest")``: the entry of rank round(q (k - 1)), ties to
    even); 0.0 for a group with none. NaN and infinite entries are left out."""
    layout = _layout(counts)
    pad = _padded(x, mask & np.isfinite(x), layout)
    if layout.width == 0:
        return np.zeros(layout.n)
    srt = np.sort(pad, axis=1)
    cnt = np.isfinite(pad).sum(axis=1)
    rank = np.clip(np.round(q * (cnt - 1)).astype(int), 0, None)
    return np.where(cnt > 0, srt[np.arange(layout.n), rank], 0.0)


def group_median_nan_propagating(
    x: np.ndarray, layout: GroupLayout, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``np.median`` of each group's entries (where ``mask``, if given), bit for bit: NaN for a
    group with a NaN among them, infinities counted as values.

    Returns:
        ((n,) medians, 0.0 for a group with no entries; (n,) entries counted).
    """
    group, n = layout.group, layout.n
    pad = np.full((n, layout.width), np.inf)  # +inf padding sorts to each row's end
    if mask is None:
        pad[group, layout.pos] = x
        cnt = np.bincount(group, minlength=n)
        nan = np.isnan(x)
    else:
        pad[group, layout.pos] = np.where(mask, x, np.inf)
        cnt = np.bincount(group, weights=mask, minlength=n).astype(np.intp)
        nan = np.isnan(x) & mask
    pad.sort(axis=1)
    med = _middle_of_sorted(pad, cnt)
    if nan.any():
        med[np.bincount(group[nan], minlength=n) > 0] = np.nan
    return med, cnt
