"""Split-conformal maths: finite-sample quantile and coverage on exchangeable data."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.conformal import conformal_quantile
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
