"""Weighted quantile bins of a table's columns, the ones scikit-learn's gradient boosting would choose, found in one pass.

``HistGradientBoostingClassifier`` bins every feature at its (weighted) quantiles before it grows
trees. With sample weights, scikit-learn (1.8–1.9) finds each of a column's 254 thresholds by a
separate call of its weighted-percentile routine, so a fit on a thousand rows spends most of its
time binning (the learned gate: 24 of 31 s in the main job, under cProfile). This module finds
the same thresholds for all quantiles of a column at once (one sort, one cumulative sum, one
vectorised search) and maps values to their bin numbers. Boosting on the bin numbers then grows
the trees it would grow on the values, and predicts the same, provided every bin holds a
training value (``BinnedColumns.binned_``): the classifier's own binning of whole numbers
0, 1, …, k is those numbers, and its threshold between bins ``b`` and ``b + 1`` separates the
same values as the threshold found here. Where an inner bin is empty (a quantile falling on a
boundary of the weights), a threshold between two non-adjacent bin numbers would not; an empty
top bin (a heavy largest value) is harmless unless the column has missing values. Such a column
is handed over as it is, and the classifier bins it itself (each column is binned on its own).

The rule for each column (scikit-learn's ``_find_binning_thresholds``, facts not code): NaN and
zero-weight values are left out; a column with one distinct value has no threshold; one with at
most ``max_bins`` distinct values is cut at the midpoints between them; otherwise at the
percentiles ``100·j / max_bins`` (j = 1 … max_bins − 1), "averaged inverted CDF" (the value where
the cumulative weight first reaches the rank, averaged with the next value when the rank falls on
a boundary within machine epsilon); repeated thresholds are merged and none exceeds the largest
finite double. A value ``v`` is in bin ``i`` when ``t[i-1] < v <= t[i]``; NaN stays NaN.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

#: The largest threshold a column may have (scikit-learn keeps +inf for "split on NaN").
_LARGEST = np.finfo(np.float64).max


def column_thresholds(values: np.ndarray, weights: np.ndarray | None, max_bins: int = 255) -> np.ndarray:
    """Increasing thresholds that cut one column into at most ``max_bins`` bins of (weighted) equal mass.

    Parameters
    ----------
    values : numpy.ndarray
        (N,) the column's values (NaN: missing, ignored).
    weights : numpy.ndarray or None
        (N,) non-negative sample weights; None: every value weighs the same.
    max_bins : int
        Bins for the non-missing values (scikit-learn's default is 255).

    Returns
    -------
    numpy.ndarray
        (≤ max_bins − 1,) float64 thresholds (module docstring).
    """
    values = np.asarray(values, dtype=np.float64)
    keep = ~np.isnan(values)
    if weights is not None:
        weights = np.asarray(weights, dtype=np.float64)
        keep &= weights != 0
        weights = weights[keep]
    values = values[keep]
    order = np.argsort(values)
    values = values[order]
    distinct = np.unique(values)
    if distinct.size <= 1:
        return np.empty(0)
    if distinct.size <= max_bins:
        thresholds = (distinct[:-1] + distinct[1:]) / 2
    else:
        ranks = np.linspace(0, 100, num=max_bins + 1)[1:-1]
        if weights is None:
            thresholds = np.percentile(values, ranks, method="averaged_inverted_cdf")
        else:
            thresholds = _weighted_averaged_inverted_cdf(values, weights[order], ranks)
        thresholds = np.unique(thresholds)
    return np.minimum(thresholds, _LARGEST)


def _weighted_averaged_inverted_cdf(sorted_values: np.ndarray, weights: np.ndarray, ranks: np.ndarray) -> np.ndarray:
    """Weighted "averaged inverted CDF" percentiles (Hyndman & Fan 1996, definition 2) of sorted, positively weighted values."""
    # scikit-learn sorts the (already sorted) values once more before accumulating their weights: ties may be
    # reordered, which moves where a rank falls inside a run of equal values, so the same second sort is kept
    again = np.argsort(sorted_values)
    cdf = np.cumsum(weights[again])
    target = ranks / 100 * cdf[-1]
    target = np.where(target == 0, np.nextafter(target, target + 1), target)
    last = sorted_values.size - 1
    at = np.clip(np.searchsorted(cdf, target), 0, last)
    value = sorted_values[again[at]]
    following = sorted_values[again[np.clip(at + 1, 0, last)]]
    above = cdf[at] - target > np.finfo(np.float64).eps
    return np.where(above, value, (value + following) / 2)


class BinnedColumns:
    """Bin numbers of a table's columns at their (weighted) quantiles (module docstring).

    Parameters
    ----------
    max_bins : int
        Bins per column for the non-missing values.

    Attributes
    ----------
    columns_ : list of str
        The columns, in the order fitted.
    thresholds_ : list of numpy.ndarray
        Each column's thresholds.
    binned_ : list of bool
        Per column, whether it is given as bin numbers: where boosting on them grows and predicts
        as on the values (module docstring); a column where it would not is given as it is, and
        the classifier bins it itself.
    """

    def __init__(self, max_bins: int = 255) -> None:
        self.max_bins = int(max_bins)

    def fit(self, table: pd.DataFrame, sample_weight: np.ndarray | None = None) -> BinnedColumns:
        """Find each column's thresholds on ``table`` (rows weighted by ``sample_weight``)."""
        self.columns_ = [str(c) for c in table.columns]
        self.thresholds_ = [column_thresholds(table[c].to_numpy(np.float64), sample_weight, self.max_bins) for c in table.columns]
        # the classifier bins what it is given from the rows that weigh something, as the thresholds were found
        weighs = np.ones(len(table), dtype=bool) if sample_weight is None else np.asarray(sample_weight) != 0
        self.binned_ = [
            _grows_alike(_bin_numbers(table[c].to_numpy(np.float64), t), t, weighs)
            for c, t in zip(self.columns_, self.thresholds_, strict=True)
        ]
        return self

    def transform(self, table: pd.DataFrame) -> pd.DataFrame:
        """``table``'s columns, as bin numbers where ``binned_`` (float; NaN stays NaN), else as they are; same index and names."""
        out = {}
        for name, thresholds, binned in zip(self.columns_, self.thresholds_, self.binned_, strict=True):
            values = table[name].to_numpy(np.float64)
            out[name] = _bin_numbers(values, thresholds) if binned else values
        return pd.DataFrame(out, index=table.index)


def _bin_numbers(values: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Bin ``i`` for ``thresholds[i-1] < value <= thresholds[i]`` (float), NaN for NaN."""
    return np.where(np.isnan(values), np.nan, np.searchsorted(thresholds, values, side="left").astype(np.float64))


def _grows_alike(numbers: np.ndarray, thresholds: np.ndarray, weighs: np.ndarray) -> bool:
    """Whether boosting on a column's bin ``numbers`` splits as it would on its values (module docstring).

    Every bin must hold a weighted training value, except that the top bin may be empty (the
    last threshold is the largest value: no split can leave it on one side alone) in a column
    without missing values; with missing values the classifier's "values left, NaN right" split
    would then send values above the top threshold the other way.
    """
    present = np.unique(numbers[weighs & ~np.isnan(numbers)])
    if not np.array_equal(present, np.arange(present.size)):
        return False
    return present.size == thresholds.size + 1 or (present.size == thresholds.size and not np.isnan(numbers).any())
