"""Split-conformal maths: finite-sample quantile and coverage on exchangeable data."""

import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.conformal import conformal_quantile, grouped_conformal_quantile
from plugins.conformal.split import SplitConformal
from tests.conftest import examples


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


@settings(max_examples=examples(20), deadline=None)
@given(
    seed=st.integers(0, 2**31),
    n=st.integers(20, 200),
    level=st.sampled_from([0.5, 0.8, 0.9, 0.95]),
    normaliser=st.sampled_from(["none", "gdop", "predicted_error"]),
)
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
    # Monte-Carlo slack: 4.5 standard errors. Hypothesis draws 20 examples a CI run, so at 3 one run in twenty failed by
    # chance alone (seed 137215, n 93 at 0.5: 3.2 standard errors below); at 4.5 about one in 10,000
    mc = 4.5 * np.std(covered) / np.sqrt(reps)
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
    np.testing.assert_allclose(
        only.radius(np.array([0.1, 50.0]), np.array([2.0, 2.0]))[:, 0], only.radius(np.array([1.0, 1.0]), np.array([2.0, 2.0]))[:, 0]
    )


def test_binned_gdop_scaled_and_gdop_only_cover_on_exchangeable_data():
    rng = np.random.default_rng(0)
    reps, n, m = 300, 150, 60
    variants = {
        "gdop_scaled": SplitConformal("gdop"),
        "gdop_only": SplitConformal("gdop", use_error_model=False),
        "mondrian": SplitConformal("none", binning="gdop", n_bins=3),
    }
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


def test_region_binning_covers_inside_and_far_where_one_quantile_cannot():
    # errors 6x larger far outside the hull than inside it, GDOP uninformative: one quantile over-covers inside, under-covers far
    rng = np.random.default_rng(1)
    reps, n, m = 300, 300, 150
    hits = {"none": {0: [], 2: []}, "region": {0: [], 2: []}}
    for _ in range(reps):
        hull = rng.choice([-0.0, 0.3, 1.0], size=n + m, p=[0.6, 0.2, 0.2])
        err = np.where(hull > 0.5, 6.0, 1.0) * rng.exponential(size=n + m)
        pred, g = np.ones(n + m), np.ones(n + m)
        for binning in hits:
            scorer = SplitConformal("none", binning=binning).fit(err[:n], pred[:n], g[:n], [0.8], hull_distance=hull[:n])
            covered = err[n:] <= scorer.radius(pred[n:], g[n:], hull_distance=hull[n:])[:, 0]
            for region, rows in ((0, hull[n:] <= 0), (2, hull[n:] > 0.5)):
                hits[binning][region].append(covered[rows].mean())
    assert 0.78 <= np.mean(hits["region"][0]) <= 0.84 and 0.78 <= np.mean(hits["region"][2]) <= 0.86
    assert np.mean(hits["none"][2]) < 0.6 and np.mean(hits["none"][0]) > 0.9
    assert SplitConformal(binning="region").needs_hull_distance and not SplitConformal(binning="gdop").needs_hull_distance
    with pytest.raises(ValueError, match="hull_distance"):
        SplitConformal(binning="region").fit(np.ones(9), np.ones(9), np.ones(9), [0.8])


@pytest.mark.parametrize("normaliser", ["none", "gdop", "predicted_error"])
@pytest.mark.parametrize("binning", ["none", "gdop"])
def test_same_intervals_as_crepes(normaliser, binning):
    """The absolute score reproduces crepes' (Mondrian, normalised) conformal regressor for every normaliser × binning."""
    crepes = pytest.importorskip("crepes")
    rng = np.random.default_rng(1)
    err, pred, g = rng.lognormal(size=300), rng.uniform(0.5, 2, 300), rng.uniform(1, 5, 300)
    ours = SplitConformal(normaliser, binning=binning, n_bins=3, score="absolute", gdop_cap_quantile=None).fit(err, pred, g, [0.8, 0.95])
    sigma = {"none": np.ones_like(pred), "gdop": g / np.median(g), "predicted_error": pred}[normaliser]
    bins = ours._bins(pred, g) if binning != "none" else None
    cr = crepes.ConformalRegressor().fit(residuals=err - pred, sigmas=sigma, bins=bins)
    test_pred, test_g = rng.uniform(0.5, 2, 8), rng.uniform(1, 5, 8)
    test_sigma = {"none": np.ones(8), "gdop": test_g / np.median(g), "predicted_error": test_pred}[normaliser]
    test_bins = ours._bins(test_pred, test_g) if binning != "none" else None
    for k, level in enumerate([0.8, 0.95]):
        interval = cr.predict_int(y_hat=test_pred, sigmas=test_sigma, bins=test_bins, confidence=level)
        np.testing.assert_allclose(ours.radius(test_pred, test_g)[:, k], np.maximum(interval[:, 1], 0), rtol=1e-9)


def test_ellipse_coverage_on_exchangeable_synthetic_data():
    """Errors drawn from the local TDOA covariance (anisotropic outside the array) scaled by ê: the calibrated
    ellipses cover at the nominal level, and they are thinner than the circle of the same coverage."""
    from acoustlab.toolkit.conformal import conformal_quantile
    from acoustlab.toolkit.regions import ellipse_axes, inside_ellipse, mahalanobis, shape_matrices

    mics = np.array([[0.0, 0.0, 1.2], [50.0, 0.0, 1.2], [24.0, 44.0, 1.2]])
    rng = np.random.default_rng(0)
    hits, areas, circle_areas = [], [], []
    for _ in range(60):
        n, m = 300, 100
        pos = rng.uniform(-40, 90, size=(n + m, 2))
        pred = rng.uniform(0.5, 3.0, n + m)
        shape = shape_matrices(mics, pos, 1.2)
        d = np.einsum("bij,bj->bi", np.linalg.cholesky(shape), rng.normal(size=(n + m, 2))) * pred[:, None]
        q = conformal_quantile(mahalanobis(d[:n], shape[:n]) / pred[:n], 0.8)
        a, b, angle = ellipse_axes(shape[n:], q * pred[n:])
        hits.append(inside_ellipse(d[n:], a, b, angle).mean())
        areas.append(np.median(np.pi * a * b))
        r = conformal_quantile(np.linalg.norm(d[:n], axis=1), 0.8)
        circle_areas.append(np.pi * r**2)
    assert 0.78 <= np.mean(hits) <= 0.83
    assert np.median(areas) < np.median(circle_areas)


def test_a_failed_event_is_never_inside_its_ellipse_and_raises_no_warning():
    """Failures carry infinite error vectors: they count as not covered, without NaN arithmetic warnings."""
    import warnings

    from acoustlab.toolkit.regions import inside_ellipse

    error = np.array([[0.5, 0.0], [np.inf, np.inf], [0.0, 2.0], [np.nan, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        inside = inside_ellipse(error, np.array([1.0, 1.0, 1.0, 1.0]), np.array([1.0, 1.0, 1.0, 1.0]), np.array([90.0, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(inside, [True, False, False, False])


@pytest.mark.slow
def test_selective_threshold_controls_the_gross_share_among_placed_events():
    """Learn then Test: over many exchangeable draws, the share of gross errors among the placed test events
    exceeds δ in at most about ε of them; a stricter δ places fewer events."""
    from acoustlab.toolkit.conformal import selective_threshold

    rng = np.random.default_rng(0)
    delta, epsilon, violations, placed = 0.05, 0.1, [], []
    for _ in range(200):
        score = rng.uniform(0, 1, 3000)
        gross = rng.random(3000) < score**3  # higher predicted error, more gross errors
        t, path = selective_threshold(score[:1000], gross[:1000], delta, epsilon)
        keep = score[1000:] <= t
        placed.append(keep.mean())
        violations.append(gross[1000:][keep].mean() > delta if keep.any() else False)
        assert all(p["p_value"] <= epsilon for p in path[:-1])
    assert np.mean(violations) <= epsilon + 0.05
    assert 0.3 < np.mean(placed) < 0.9
    strict, _ = selective_threshold(score[:1000], gross[:1000], 0.01, epsilon)
    assert strict < t


def test_selective_threshold_refuses_when_nothing_can_be_certified():
    from acoustlab.toolkit.conformal import selective_threshold

    t, path = selective_threshold(np.linspace(0, 1, 50), np.ones(50, bool), 0.01, 0.1)
    assert t == -np.inf and len(path) <= 1
    with pytest.raises(ValueError, match="delta"):
        selective_threshold(np.zeros(3), np.zeros(3, bool), 1.5, 0.1)


def _heteroscedastic(rng, n):
    """Errors whose spread grows with a feature the quantile model can see (GDOP alone cannot)."""
    x = rng.uniform(0.0, 1.0, size=(n, 2))
    error = (0.2 + 3.0 * x[:, 0]) * rng.exponential(1.0, size=n)
    return pd.DataFrame(x, columns=["a", "b"]), error


def test_cqr_covers_and_adapts_where_fixed_cannot():
    from sklearn.ensemble import HistGradientBoostingRegressor
    from xgboost import XGBRegressor

    from plugins.conformal.cqr import ConformalizedQuantile

    rng = np.random.default_rng(11)
    levels = [0.5, 0.8, 0.95]
    x_fit, e_fit = _heteroscedastic(rng, 3000)
    x_cal, e_cal = _heteroscedastic(rng, 3000)
    x_test, e_test = _heteroscedastic(rng, 6000)
    predicted_cal, predicted_test = np.full(len(e_cal), np.median(e_fit)), np.full(len(e_test), np.median(e_fit))
    gdop_cal, gdop_test = np.ones(len(e_cal)), np.ones(len(e_test))
    fixed = SplitConformal().fit(e_cal, predicted_cal, gdop_cal, levels)
    for model in (
        XGBRegressor(objective="reg:quantileerror", n_estimators=100, max_depth=3, n_jobs=1),
        HistGradientBoostingRegressor(loss="quantile", max_iter=100),
    ):
        cqr = ConformalizedQuantile(model)
        q_all = cqr.fit_predict_quantiles(x_fit, e_fit, pd.concat([x_cal, x_test]), levels)
        cqr.fit(e_cal, predicted_cal, gdop_cal, levels, quantiles=q_all[: len(e_cal)])
        radii = cqr.radius(predicted_test, gdop_test, quantiles=q_all[len(e_cal) :])
        assert (np.diff(radii, axis=1) >= 0).all()
        for k, level in enumerate(levels):
            assert abs(np.mean(e_test <= radii[:, k]) - level) < 0.03, (type(model).__name__, level)
        # where the spread is small, CQR's radius is smaller than the fixed one; where it is large, larger
        quiet, loud = x_test["a"].to_numpy() < 0.2, x_test["a"].to_numpy() > 0.8
        fixed_radius = fixed.radius(predicted_test, gdop_test)[:, 2]
        assert np.median(radii[quiet, 2]) < 0.6 * np.median(fixed_radius[quiet])
        assert np.median(radii[loud, 2]) > np.median(fixed_radius[loud])
        # and the coverage within the loud region, which fixed misses, holds much better
        assert np.mean(e_test[loud] <= radii[loud, 2]) > np.mean(e_test[loud] <= fixed_radius[loud]) + 0.05


def test_cqr_without_quantiles_is_fixed():
    from xgboost import XGBRegressor

    from plugins.conformal.cqr import ConformalizedQuantile

    rng = np.random.default_rng(2)
    error, predicted, gdop = rng.exponential(1.0, 500), rng.uniform(0.5, 2.0, 500), rng.uniform(1, 3, 500)
    cqr = ConformalizedQuantile(XGBRegressor(objective="reg:quantileerror")).fit(error, predicted, gdop, [0.5, 0.9])
    fixed = SplitConformal().fit(error, predicted, gdop, [0.5, 0.9])
    np.testing.assert_allclose(cqr.radius(predicted, gdop), fixed.radius(predicted, gdop))


def test_cqr_calibrated_over_positions_weighs_each_position_the_same():
    """One spot with 40 large-error playbacks beside 9 with 2 each: over events that spot dominates the correction, over
    positions it weighs 1/10 (the field's calibration is position-level for CQR too)."""
    from xgboost import XGBRegressor

    from plugins.conformal.cqr import ConformalizedQuantile

    groups = np.r_[np.zeros(40), np.repeat(np.arange(1, 10), 2)]
    error = np.where(groups == 0, 5.0, 0.5) + np.linspace(0, 0.1, groups.size)
    predicted, gdop = np.zeros(groups.size), np.ones(groups.size)
    model = XGBRegressor(objective="reg:quantileerror")
    by_event = ConformalizedQuantile(model).fit(error, predicted, gdop, [0.5, 0.8])
    by_position = ConformalizedQuantile(model, calibration_unit="position").fit(error, predicted, gdop, [0.5, 0.8], groups=groups)
    assert by_event.corrections_[0] >= 5.0  # most events are the one spot's
    np.testing.assert_array_equal(by_position.corrections_, [grouped_conformal_quantile(error, groups, v) for v in (0.5, 0.8)])
    assert by_position.corrections_[0] < 1.0
    with pytest.raises(ValueError, match="needs the calibration events' positions"):
        ConformalizedQuantile(model, calibration_unit="position").fit(error, predicted, gdop, [0.5])


def test_cqr_rejects_a_model_without_quantiles():
    from sklearn.linear_model import LinearRegression

    from plugins.conformal.cqr import ConformalizedQuantile

    with pytest.raises(ConfigError, match="not a quantile regressor"):
        ConformalizedQuantile(LinearRegression())


def test_position_level_calibration_covers_new_positions_where_event_level_does_not():
    """One position with 100× the events of the others: calibrating over positions covers a new position, over events it does not."""

    rng = np.random.default_rng(0)
    level, n_positions = 0.8, 30
    covered = {"event": [], "position": []}
    for _ in range(400):
        scale = rng.lognormal(0.0, 1.0, n_positions)  # each position's own error scale
        counts = np.full(n_positions, 3)
        counts[0] = 300  # one spot with many playbacks (a scale drawn like every other position's)
        groups = np.repeat(np.arange(n_positions), counts)
        scores = np.abs(rng.normal(0, scale[groups]))
        q_event = conformal_quantile(scores, level)
        q_position = grouped_conformal_quantile(scores, groups, level)
        new = np.abs(rng.normal(0, rng.lognormal(0.0, 1.0)))  # an event of a new position, like the others
        covered["event"].append(new <= q_event)
        covered["position"].append(new <= q_position)
    assert np.mean(covered["position"]) >= level - 0.05
    assert np.mean(covered["event"]) <= level - 0.07  # 0.70 with this seed


def test_position_level_quantile_needs_enough_positions():

    scores, groups = np.arange(40.0), np.repeat(np.arange(10), 4)
    assert grouped_conformal_quantile(scores, groups, 0.95) == np.inf  # 10 positions cannot support 0.95 (19 needed)
    assert np.isfinite(grouped_conformal_quantile(scores, groups, 0.9))
    # equal events per position: the same as weighing events equally with the n + 1 correction over positions
    assert grouped_conformal_quantile(scores, groups, 0.5) == np.sort(scores)[int(np.ceil(0.5 * 11 / 10 * 40)) - 1]
    scorer = SplitConformal(calibration_unit="position").fit(scores, np.zeros(40), np.ones(40), [0.5, 0.95], groups=groups)
    assert np.isinf(scorer.quantiles_[0, 1]) and np.isfinite(scorer.quantiles_[0, 0])


def test_subsampled_position_quantile_covers_a_new_spot_in_finite_samples():
    """5 spots, clustered errors (each spot its own scale and bias), unequal playbacks: ≥ 0.8 coverage of a new spot's call."""
    from acoustlab.toolkit.conformal import subsampled_position_quantile

    rng = np.random.default_rng(1)
    level, n_spots, covered, event_level = 0.8, 5, [], []
    for _ in range(4000):
        scale, bias = rng.lognormal(-1.0, 0.5, n_spots + 1), rng.normal(0.0, 3.0, n_spots + 1)  # spots differ more than calls
        counts = rng.integers(5, 40, n_spots)
        groups = np.repeat(np.arange(n_spots), counts)
        scores = bias[groups] + scale[groups] * rng.normal(0, 1, groups.size)
        new = bias[-1] + scale[-1] * rng.normal()
        covered.append(new <= subsampled_position_quantile(scores, groups, level, seed=int(rng.integers(1 << 30))))
        event_level.append(new <= conformal_quantile(scores, level))
    assert np.mean(covered) >= level - 0.015  # the finite-sample guarantee (Monte Carlo error ≈ 0.006)
    assert np.mean(event_level) < level - 0.03  # events of one spot are not independent draws (0.76 here)


def test_pooled_position_quantile_covers_a_new_spot_in_finite_samples():
    """The pooled per-spot CDFs with the new spot's share at +∞: ≥ 0.8 with 5 spots, clustered errors, unequal playbacks."""
    rng = np.random.default_rng(1)
    level, n_spots, covered = 0.8, 5, []
    for _ in range(4000):
        scale, bias = rng.lognormal(-1.0, 0.5, n_spots + 1), rng.normal(0.0, 3.0, n_spots + 1)
        counts = rng.integers(5, 40, n_spots)
        groups = np.repeat(np.arange(n_spots), counts)
        scores = bias[groups] + scale[groups] * rng.normal(0, 1, groups.size)
        covered.append(bias[-1] + scale[-1] * rng.normal() <= grouped_conformal_quantile(scores, groups, level))
    assert np.mean(covered) >= level - 0.015  # finite-sample (Lee, Barber & Willett 2023); Monte Carlo error ≈ 0.006


def test_pooling_every_playback_scatters_less_than_one_per_spot():
    """One calibration set's coverage of new spots' calls, over 600 sets of 10 spots × 5 playbacks: both hold the level
    on average; pooling every playback gives a narrower 5–95 % range than one playback per spot."""
    from acoustlab.toolkit.conformal import subsampled_position_quantile

    rng = np.random.default_rng(2)

    def spots(n: int) -> np.ndarray:  # (n, 5) scores: each spot its own bias and scale
        return rng.standard_cauchy((n, 1)) * 0.3 + rng.exponential(1.0, (n, 1)) * rng.standard_normal((n, 5))

    new_calls = spots(20000).ravel()
    groups = np.repeat(np.arange(10), 5)
    pooled, subsampled = [], []
    for k in range(600):
        scores = spots(10).ravel()
        pooled.append(np.mean(new_calls <= grouped_conformal_quantile(scores, groups, 0.5)))
        subsampled.append(np.mean(new_calls <= subsampled_position_quantile(scores, groups, 0.5, seed=k)))
    assert np.mean(pooled) >= 0.5 - 0.01 and np.mean(subsampled) >= 0.5 - 0.015
    width = {name: np.subtract(*np.quantile(v, [0.95, 0.05])) for name, v in (("pooled", pooled), ("subsampled", subsampled))}
    assert width["pooled"] < 0.85 * width["subsampled"], width


def test_subsampled_position_quantile_is_the_same_whatever_the_rows_order():
    from acoustlab.toolkit.conformal import positions_needed, subsampled_position_quantile

    rng = np.random.default_rng(2)
    scores, groups = rng.normal(size=60), np.repeat(np.arange(20), 3)
    order = rng.permutation(60)
    assert subsampled_position_quantile(scores, groups, 0.9, 3) == subsampled_position_quantile(scores[order], groups[order], 0.9, 3)
    assert [positions_needed(v) for v in (0.5, 0.8, 0.9, 0.95)] == [1, 4, 9, 19]
    assert np.isinf(subsampled_position_quantile(scores, groups, 0.96))  # 20 spots cannot give 0.96 (24 needed)


def test_coverage_by_condition_shows_where_radii_fail():
    """Radii that hold where GDOP is small and fail where it is large: the breakdown says so, bin by bin, per detection and position."""
    from acoustlab.reporting.metrics import coverage_by_condition

    rng = np.random.default_rng(0)
    n = 400
    gdop = np.where(np.arange(n) < 300, 1.0, 30.0)
    error = np.where(gdop > 20, 5.0, 0.5) * rng.uniform(0.5, 1.5, n)
    p = pd.DataFrame(
        {
            col.error_m("gate"): error,
            col.radius("fixed", 0.8): np.full(n, 1.0),
            "gdop": gdop,
            col.POSITION_ID: np.arange(n) // 4,
            col.HULL_DISTANCE: np.where(np.arange(n) % 2 == 0, 0.0, 0.4),
        }
    )
    out = coverage_by_condition(p, [0.8], ["fixed"])
    by_bin = {row["bin"]: row for row in out["gdop"]}
    assert by_bin["(0, 2]"]["fixed@0.8"]["detections"] == 1.0 and by_bin["(0, 2]"]["n"] == 300
    assert by_bin["(20, inf]"]["fixed@0.8"] == {"detections": 0.0, "positions": 0.0}
    assert [row["bin"] for row in out["hull_distance"]] == ["(-inf, 0]", "(0.25, 0.5]"]
    assert "snr_db" not in out  # no SNR column: no breakdown by it


def _clustered_calls(rng: np.random.Generator, n_positions: int, per: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted errors and gross flags where a gross error hits every call of a position (a mirror fix, a bad spot)."""
    difficulty = rng.uniform(0, 1, n_positions)
    bad = rng.random(n_positions) < 0.25 * difficulty**2
    groups = np.repeat(np.arange(n_positions), per)
    return difficulty[groups] + rng.normal(0, 0.15, groups.size), bad[groups], groups


@pytest.mark.slow
def test_the_position_level_certificate_holds_when_gross_errors_cluster_by_position():
    """δ = 5 %, ε = 0.1: counting calls as independent fails the guarantee ~20 % of the time; by position it never does here."""
    from acoustlab.toolkit.conformal import selective_threshold, selective_threshold_by_position

    rng = np.random.default_rng(0)
    score, gross, _ = _clustered_calls(rng, 100_000)

    def risk(t: float) -> float:
        placed = score <= t
        return float((placed & gross).sum() / max(placed.sum(), 1))

    delta, epsilon, reps = 0.05, 0.1, 60
    failed = {"event": 0, "position": 0}
    certified = 0
    for _ in range(reps):
        s, g, groups = _clustered_calls(rng, 800)
        by_event, _ = selective_threshold(s, g, delta, epsilon)
        by_position, path = selective_threshold_by_position(s, g, groups, delta, epsilon)
        failed["event"] += np.isfinite(by_event) and risk(by_event) > delta
        failed["position"] += np.isfinite(by_position) and risk(by_position) > delta
        certified += np.isfinite(by_position)
    assert failed["position"] / reps <= epsilon
    assert failed["event"] / reps >= 0.12  # the event-level certificate's overconfidence on clustered errors
    assert certified >= reps // 3  # it does certify something with 800 positions


def test_both_scorers_refuse_an_unknown_calibration_unit_or_method_in_one_line():
    from sklearn.ensemble import GradientBoostingRegressor

    from plugins.conformal.cqr import ConformalizedQuantile

    with pytest.raises(ConfigError, match="calibration_unit must be 'event' or 'position'; got 'spot'"):
        SplitConformal(calibration_unit="spot")
    with pytest.raises(ConfigError, match="position_method must be 'pooled', 'subsample' or 'pac'; got 'mean'"):
        SplitConformal(calibration_unit="position", position_method="mean")
    with pytest.raises(ConfigError, match="calibration_unit must be 'event' or 'position'; got 'spot'"):
        ConformalizedQuantile(GradientBoostingRegressor(loss="quantile"), calibration_unit="spot")
    with pytest.raises(ValueError, match="needs the calibration events' positions"):
        ConformalizedQuantile(GradientBoostingRegressor(loss="quantile"), calibration_unit="position").fit(
            np.ones(5), np.ones(5), np.ones(5), [0.5], quantiles=np.ones((5, 1))
        )


@pytest.mark.parametrize("n_spots, level", [(10, 0.5), (10, 0.8), (20, 0.8), (25, 0.95)])
def test_the_one_set_statement_is_the_beta_quantile_for_subsample_and_a_lower_bound_for_pooled(n_spots, level):
    """'With probability 0.9 over your spots, this radius covers at least c': over 1,500 sets of spots × 5 calls with a
    bias per spot, c is the 10 % quantile of one subsampled set's coverage of a new spot's call (within Monte Carlo
    error), and pooling every call does at least as well."""
    from scipy.stats import norm

    from acoustlab.toolkit.conformal import one_set_coverage, subsampled_position_quantile

    rng = np.random.default_rng(n_spots * 100 + int(100 * level))
    spread = np.hypot(0.7, 0.5)  # a call's log-error: the spot's bias (0.7) plus its own (0.5)

    def coverage(radius: float) -> float:  # of a random call at a new spot, exactly
        return float(norm.cdf(np.log(radius) / spread)) if np.isfinite(radius) else 1.0

    groups = np.repeat(np.arange(n_spots), 5)
    subsampled, pooled = [], []
    for k in range(1500):
        scores = np.exp(np.repeat(rng.normal(0, 0.7, n_spots), 5) + rng.normal(0, 0.5, groups.size))
        subsampled.append(coverage(subsampled_position_quantile(scores, groups, level, seed=k)))
        pooled.append(coverage(grouped_conformal_quantile(scores, groups, level)))
    stated = one_set_coverage(n_spots, level)
    assert stated == pytest.approx(np.quantile(subsampled, 0.1), abs=0.03)
    assert np.quantile(pooled, 0.1) >= stated - 0.01
    assert one_set_coverage(18, 0.95) is None  # 19 spots needed for a 0.95 radius at all


def test_a_region_without_calibration_events_says_why_its_radius_is_infinite():
    """Mondrian by region with every calibration spot inside the array: far detections get an infinite radius and a
    note naming the region and its (zero) calibration events; inside ones neither."""
    rng = np.random.default_rng(0)
    err = rng.exponential(size=40)
    scorer = SplitConformal("none", binning="region").fit(err, np.ones(40), np.ones(40), [0.5, 0.8], hull_distance=np.zeros(40))
    hull = np.array([0.0, 2.0])
    radii = scorer.radius(np.ones(2), np.ones(2), hull_distance=hull)
    notes = scorer.radius_notes(np.ones(2), np.ones(2), hull_distance=hull)
    assert np.isfinite(radii[0]).all() and np.isinf(radii[1]).all()
    assert notes.tolist() == ["", "radius at 0.5, 0.8 infinite: 0 calibration events farther outside the array"]
    assert (SplitConformal("none").fit(err, np.ones(40), np.ones(40), [0.8]).radius_notes(np.ones(2), np.ones(2)) == "").all()


@pytest.mark.parametrize("n_spots, level", [(10, 0.8), (25, 0.95), (40, 0.8)])
def test_a_pac_radius_covers_level_minus_epsilon_for_all_but_delta_of_the_sets(n_spots, level):
    """``position_method: pac``: over 2,000 sets of spots × 5 calls with a bias per spot, one set's coverage of a new
    spot's call falls below ℓ − ε in at most δ of the sets (the marginal rank's in as many or more); the one-set statement is
    ≥ ℓ − ε; fewer spots than ``pac_positions_needed`` give no finite radius."""
    from scipy.stats import norm

    from acoustlab.toolkit.conformal import one_set_coverage, pac_positions_needed, subsampled_position_quantile

    delta, epsilon = 0.1, 0.05
    rng = np.random.default_rng(n_spots)
    spread = np.hypot(0.7, 0.5)
    groups = np.repeat(np.arange(n_spots), 5)
    pac, marginal = [], []
    for k in range(2000):
        scores = np.exp(np.repeat(rng.normal(0, 0.7, n_spots), 5) + rng.normal(0, 0.5, groups.size))
        scorer = SplitConformal("none", use_error_model=False, calibration_unit="position", position_method="pac", seed=k)
        radius = scorer.fit(scores, np.zeros(groups.size), np.ones(groups.size), [level], groups=groups).quantiles_[0, 0]
        pac.append(norm.cdf(np.log(radius) / spread))
        marginal.append(norm.cdf(np.log(subsampled_position_quantile(scores, groups, level, seed=k)) / spread))
    short = np.mean(np.array(pac) < level - epsilon)
    assert short <= delta + 0.02  # Monte Carlo error ≈ 0.007
    assert np.mean(np.array(marginal) < level - epsilon) >= short  # the same rank where the set is small (25 spots at 0.95)
    assert one_set_coverage(n_spots, level, method="pac") >= level - epsilon
    needed = pac_positions_needed(level, delta, epsilon)
    assert (needed, pac_positions_needed(0.8, delta, epsilon), pac_positions_needed(0.95, delta, epsilon)) == (needed, 9, 22)
    few = np.exp(rng.normal(0, 1, (needed - 1) * 5))
    scorer = SplitConformal("none", use_error_model=False, calibration_unit="position", position_method="pac")
    assert np.isinf(
        scorer.fit(few, np.zeros(few.size), np.ones(few.size), [level], groups=np.repeat(np.arange(needed - 1), 5)).quantiles_
    ).all()


def test_pac_settings_are_checked_in_one_line():
    with pytest.raises(ConfigError, match="pac_delta must lie in"):
        SplitConformal(position_method="pac", pac_delta=1.5)
    with pytest.raises(ConfigError, match="pac_epsilon must lie in"):
        SplitConformal(position_method="pac", pac_epsilon=-0.1)


def test_ellipses_calibrated_on_field_spots_take_the_position_level_quantile():
    """Under a field calibration the ellipses' guarantee is over spots, as the radii's: with the calibration rows' position
    ids their size is the pooled-CDF quantile over positions (``grouped_conformal_quantile``); a method saved without them,
    the event-level one. One spot with many bad events pulls the event quantile up, not the position one."""
    from types import SimpleNamespace

    import pandas as pd

    from acoustlab.core import columns as col
    from acoustlab.method.fitted import FittedMethod
    from acoustlab.toolkit.conformal import conformal_quantile, grouped_conformal_quantile
    from acoustlab.toolkit.regions import mahalanobis, shape_matrices
    from tests.test_pipeline_calibration import site3

    site = site3()
    rng = np.random.default_rng(3)
    groups = np.r_[np.repeat(np.arange(20), 3), np.full(40, 20)]  # 20 spots of 3 calls, one spot of 40 calls
    position = rng.uniform(5, 35, (groups.size, 2))
    error = rng.normal(0, 1.0, (groups.size, 2)) * np.where(groups == 20, 4.0, 1.0)[:, None]
    predicted, height = np.ones(groups.size), np.full(groups.size, 1.5)
    scores = mahalanobis(error, shape_matrices(site.mic_positions_m, position, height))
    for stored, expected in ((groups, grouped_conformal_quantile(scores, groups, 0.8)), (None, conformal_quantile(scores, 0.8))):
        out = pd.DataFrame(index=range(1))
        holder = SimpleNamespace(
            pipeline=SimpleNamespace(c=SimpleNamespace(site=site, levels=[0.8])),
            ellipse_calibration=(error, position, predicted, height, stored),
        )
        at = np.array([[20.0, 20.0]])
        FittedMethod._add_ellipses(holder, out, at, np.ones(1), pd.DataFrame({col.SOLVER_SOURCE_HEIGHT: [1.5]}))
        shape = shape_matrices(site.mic_positions_m, at, 1.5)
        assert out[col.ellipse(0.8, "a_m")].iloc[0] == pytest.approx(expected * np.sqrt(np.linalg.eigvalsh(shape)[0, 1]))
    assert grouped_conformal_quantile(scores, groups, 0.8) < conformal_quantile(scores, 0.8)
