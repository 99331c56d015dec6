"""Split-conformal maths: finite-sample quantile and coverage on exchangeable data."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.toolkit.conformal import conformal_quantile
from plugins.conformal.fixed import FixedConformal


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
@given(seed=st.integers(0, 2**31), n=st.integers(20, 200), level=st.sampled_from([0.5, 0.8, 0.9, 0.95]))
def test_fixed_conformal_covers_on_exchangeable_data(seed, n, level):
    """Average coverage over many draws lies in [1−α, 1−α + 1/(n+1)] (up to Monte-Carlo error)."""
    rng = np.random.default_rng(seed)
    reps, m = 400, 50
    err = rng.lognormal(size=(reps, n + m))
    pred = np.ones_like(err)
    covered = []
    for r in range(reps):
        scorer = FixedConformal().fit(err[r, :n], pred[r, :n], pred[r, :n], [level])
        radius = scorer.radius(pred[r, n:], pred[r, n:])[:, 0]
        covered.append(np.mean(err[r, n:] <= radius))
    mean = float(np.mean(covered))
    mc = 3 * np.std(covered) / np.sqrt(reps)
    assert level - mc <= mean <= level + 1 / (n + 1) + mc


def test_gdop_scaled_and_mondrian_cover_on_exchangeable_data():
    from plugins.conformal.gdop_scaled import GdopScaledConformal
    from plugins.conformal.mondrian import MondrianGdopConformal

    rng = np.random.default_rng(0)
    reps, n, m = 300, 150, 60
    hits = {"gdop": [], "mondrian": []}
    for _ in range(reps):
        g = rng.uniform(1, 10, n + m)
        err = g * rng.lognormal(size=n + m)  # error grows with GDOP
        pred = np.ones(n + m)
        gs = GdopScaledConformal().fit(err[:n], pred[:n], g[:n], [0.8])
        mo = MondrianGdopConformal(3).fit(err[:n], pred[:n], g[:n], [0.8])
        hits["gdop"].append(np.mean(err[n:] <= gs.radius(pred[n:], g[n:])[:, 0]))
        hits["mondrian"].append(np.mean(err[n:] <= mo.radius(pred[n:], g[n:])[:, 0]))
    assert 0.78 <= np.mean(hits["gdop"]) <= 0.82 + 1 / (n + 1)
    assert 0.78 <= np.mean(hits["mondrian"]) <= 0.84


def test_same_intervals_as_crepes():
    crepes = pytest.importorskip("crepes")
    from plugins.conformal.gdop_scaled import GdopScaledConformal

    rng = np.random.default_rng(1)
    err, pred, g = rng.lognormal(size=200), rng.uniform(0.5, 2, 200), rng.uniform(1, 5, 200)
    ours = FixedConformal().fit(err, pred, g, [0.8, 0.95])
    # crepes on residuals with sigmas = the error model's output (normalised conformal regression)
    cr = crepes.ConformalRegressor().fit(residuals=err, sigmas=pred)
    test_pred, test_sig = np.zeros(5), rng.uniform(0.5, 2, 5)
    for k, level in enumerate([0.8, 0.95]):
        interval = cr.predict_int(y_hat=test_pred, sigmas=test_sig, confidence=level)
        np.testing.assert_allclose(ours.radius(test_sig, test_sig)[:, k], interval[:, 1], rtol=1e-9)
    gs = GdopScaledConformal().fit(err, pred, g, [0.9])
    cr = crepes.ConformalRegressor().fit(residuals=err, sigmas=g)
    np.testing.assert_allclose(gs.radius(test_pred, test_sig)[:, 0], cr.predict_int(y_hat=test_pred, sigmas=test_sig, confidence=0.9)[:, 1], rtol=1e-9)
