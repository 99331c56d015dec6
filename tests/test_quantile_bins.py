"""Weighted quantile bins: boosting on the bin numbers predicts what boosting on the values predicts."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from sklearn.ensemble import HistGradientBoostingClassifier

from acoustlab.toolkit.quantile_bins import BinnedColumns, _weighted_averaged_inverted_cdf, column_thresholds


def _classifier() -> HistGradientBoostingClassifier:
    return HistGradientBoostingClassifier(max_iter=60, learning_rate=0.1, max_leaf_nodes=15, random_state=0)


def _table(rng: np.random.Generator, n: int) -> pd.DataFrame:
    table = pd.DataFrame({f"normal_{i}": rng.normal(size=n) for i in range(4)})
    table["ties"] = np.round(rng.normal(size=n), 1)  # > 255 rows, < 255 distinct values: the midpoint rule
    table["heavy_tail"] = rng.standard_cauchy(n)
    table["with_nan"] = np.where(rng.random(n) < 0.1, np.nan, rng.normal(size=n))
    return table


@pytest.mark.parametrize("weights", ["capped_cost", "integers", "none"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_boosting_on_the_bin_numbers_predicts_as_on_the_values(weights: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    train, new = _table(rng, 800), _table(rng, 400)
    new.iloc[:20] *= 50  # values far outside the training range
    label = (train["normal_0"] + 0.5 * train["ties"] + rng.normal(size=len(train)) > 0).astype(int)
    w = {
        "capped_cost": np.clip(np.abs(rng.standard_cauchy(len(train))), 1e-3, 20.0),  # the learned gate's stakes
        "integers": rng.integers(1, 4, len(train)).astype(float),  # ties in the cumulative weight
        "none": None,
    }[weights]
    bins = BinnedColumns().fit(train, w)
    on_values = _classifier().fit(train, label, sample_weight=w)
    on_bins = _classifier().fit(bins.transform(train), label, sample_weight=w)
    for table in (train, new):
        np.testing.assert_array_equal(on_bins.predict_proba(bins.transform(table)), on_values.predict_proba(table))


def test_most_columns_are_given_as_bin_numbers() -> None:
    """The fast path is the common one (else the gate would gain nothing from it)."""
    binned = [
        flag
        for rng in (np.random.default_rng(s) for s in range(10))
        for flag in BinnedColumns().fit(_table(rng, 800), np.clip(np.abs(rng.standard_cauchy(800)), 1e-3, 20.0)).binned_
    ]
    assert np.mean(binned) >= 0.8


def test_an_empty_top_bin_is_exact_only_without_missing_values() -> None:
    rng = np.random.default_rng(3)
    values = rng.normal(size=600)
    w = np.ones(600)
    w[np.argmax(values)] = 600.0  # half the weight on the largest value: the top thresholds are that value
    thresholds = column_thresholds(values, w)
    assert thresholds[-1] == values.max()  # nothing lies above the last threshold
    assert BinnedColumns().fit(pd.DataFrame({"v": values}), w).binned_ == [True]
    with_nan = np.where(np.arange(600) < 30, np.nan, values)
    w[np.nanargmax(with_nan)] = 600.0
    bins = BinnedColumns().fit(pd.DataFrame({"v": with_nan}), w)
    assert bins.binned_ == [False]  # given as values: the classifier bins it itself
    np.testing.assert_array_equal(bins.transform(pd.DataFrame({"v": with_nan}))["v"], with_nan)


def test_unit_weights_give_numpys_averaged_inverted_cdf() -> None:
    rng = np.random.default_rng(4)
    values = np.sort(np.round(rng.normal(size=1001), 2))
    ranks = np.linspace(0, 100, 256)[1:-1]
    np.testing.assert_array_equal(
        _weighted_averaged_inverted_cdf(values, np.ones(values.size), ranks), np.percentile(values, ranks, method="averaged_inverted_cdf")
    )


def test_missing_values_stay_missing_and_a_constant_column_has_one_bin() -> None:
    table = pd.DataFrame({"v": [1.0, np.nan, 3.0, 2.0], "constant": [5.0] * 4})
    bins = BinnedColumns().fit(table)
    out = bins.transform(table)
    assert np.isnan(out["v"].iloc[1]) and out["v"].iloc[[0, 3, 2]].tolist() == [0.0, 1.0, 2.0]
    assert bins.thresholds_[1].size == 0 and (out["constant"] == 0).all()
