"""Split-conformal maths: finite-sample quantile and coverage on exchangeable data."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.toolkit.conformal import conformal_quantile
from plugins.conformal.split import SplitConformal


def test_quantile_rank_is_ceil_n_plus_1_times_level():
    scores = np.arange(1.0, 20.0)  # n = 19
    assert conformal_quantile(scores, 0.5) == 10.0  # ceil(20 * 0.5) = 10th smallest
    assert conformal_quantile(scores, 0.9) == 18.0  # ceil(20 * 0.9) = 18
    assert conformal_quantile(scores, 0.96) == math.inf  # ceil(20 * 0.96) = 20 > n


def test_bad_scores_are_refused():
    with pytest.raises(ValueError, match="finite"):
        conformal_quantile(np.array([1.0, np.nan]), 0.5)
    with pytest.raises(ValueError, match="level"):
        conformal_quantile(np.array([1.0]), 1.0)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(20, 200), level=st.sampled_from([0.5, 0.8, 0.9, 0.95]),
       normaliser=st.sampled_from(["none", "gdop", "predicted_error"]))
def test_split_conformal_covers_on_exchangeable_data(seed, n, level, normaliser):
    """Average coverage over many draws lies in [1−α, 1−α + 1/(n+1)] (up to Monte-Carlo error), for every normaliser."""
    rng = np.random.default_rng(seed)
    reps, m = 300, 50
    err = rng.lognormal(size=(reps, n + m))
    pred = rng.uniform(0.5, 2.0, size=(reps, n + m))
    g = rng.uniform(1.0, 5.0, size=(reps, n + m))
    covered = []
    for r in range(reps):
        scorer = SplitConformal(normaliser=normaliser).fit(err[r, :n], pred[r, :n], g[r, :n], [level])
        radius = scorer.radius(pred[r, n:], g[r, n:])[:, 0]
        covered.append(np.mean(err[r, n:] <= radius))
    mean = float(np.mean(covered))
    mc = 3 * np.std(covered) / np.sqrt(reps)
    assert level - mc <= mean <= level + 1 / (n + 1) + mc


def test_fixed_is_one_additive_adjustment_and_gdop_scaled_scales_it():
    rng = np.random.default_rng(4)
    err, pred, g = rng.lognormal(size=300), rng.uniform(0.5, 2, 300), rng.uniform(1, 5, 300)
    fixed = SplitConformal("none").fit(err, pred, g, [0.9])
    test_pred, test_g = np.array([1.0, 3.0]), np.array([2.0, 4.0])
    r = fixed.radius(test_pred, test_g)[:, 0]
    assert r[1] - r[0] == pytest.approx(2.0)  # the same adjustment added to every prediction
    scaled = SplitConformal("gdop").fit(err, pred, g, [0.9])
    r = scaled.radius(np.array([1.0, 1.0]), test_g)[:, 0]
    assert (r[1] - 1.0) == pytest.approx(2 * (r[0] - 1.0))  # the adjustment doubles with GDOP
    only = SplitConformal("gdop", use_error_model=False).fit(err, pred, g, [0.9])
    np.testing.assert_allclose(only.radius(np.array([0.1, 50.0]), np.array([2.0, 2.0]))[:, 0], only.radius(np.array([1.0, 1.0]), np.array([2.0, 2.0]))[:, 0])


def test_binned_gdop_scaled_and_gdop_only_cover_on_exchangeable_data():
    rng = np.random.default_rng(0)
    reps, n, m = 300, 150, 60
    variants = {"gdop_scaled": SplitConformal("gdop"), "gdop_only": SplitConformal("gdop", use_error_model=False),
                "mondrian": SplitConformal("none", binning="gdop", n_bins=3)}
    hits = {k: [] for k in variants}
    for _ in range(reps):
        g = rng.uniform(1, 10, n + m)
        err = g * rng.lognormal(size=n + m)  # error grows with GDOP
        pred = np.ones(n + m)
        for name, scorer in variants.items():
            fitted = scorer.fit(err[:n], pred[:n], g[:n], [0.8])
            hits[name].append(np.mean(err[n:] <= fitted.radius(pred[n:], g[n:])[:, 0]))
    for name in variants:
        assert 0.78 <= np.mean(hits[name]) <= 0.84, name


@pytest.mark.parametrize("normaliser", ["none", "gdop", "predicted_error"])
@pytest.mark.parametrize("binning", ["none", "gdop"])
def test_same_intervals_as_crepes(normaliser, binning):
    """The absolute score reproduces crepes' (Mondrian, normalised) conformal regressor for every normaliser × binning."""
    crepes = pytest.importorskip("crepes")
    rng = np.random.default_rng(1)
    err, pred, g = rng.lognormal(size=300), rng.uniform(0.5, 2, 300), rng.uniform(1, 5, 300)
    ours = SplitConformal(normaliser, binning=binning, n_bins=3, score="absolute").fit(err, pred, g, [0.8, 0.95])
    sigma = {"none": np.ones_like(pred), "gdop": g / np.median(g), "predicted_error": pred}[normaliser]
    bins = ours._bins(pred, g) if binning != "none" else None
    cr = crepes.ConformalRegressor().fit(residuals=err - pred, sigmas=sigma, bins=bins)
    test_pred, test_g = rng.uniform(0.5, 2, 8), rng.uniform(1, 5, 8)
    test_sigma = {"none": np.ones(8), "gdop": test_g / np.median(g), "predicted_error": test_pred}[normaliser]
    test_bins = ours._bins(test_pred, test_g) if binning != "none" else None
    for k, level in enumerate([0.8, 0.95]):
        interval = cr.predict_int(y_hat=test_pred, sigmas=test_sigma, bins=test_bins, confidence=level)
        np.testing.assert_allclose(ours.radius(test_pred, test_g)[:, k], np.maximum(interval[:, 1], 0), rtol=1e-9)
