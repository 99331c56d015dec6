"""A gate hands a detection over to the point model only where the model's estimate explains the measured time differences."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from sklearn.ensemble import HistGradientBoostingRegressor

from acoustlab.core import columns as col
from acoustlab.method import trust
from acoustlab.method.pipeline import LocalizationPipeline
from acoustlab.method.trust import TrustSettings
from acoustlab.toolkit.tdoa import candidate_misfit_m
from plugins.gates.simple import ModelOnlyGate
from tests.test_pipeline_calibration import site3
from tests.test_trust import components

SPEED = 343.0


def lags_s(source_xyz: np.ndarray, mics: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    """(E, P) exact lags t_j − t_i of each pair, s."""
    distance = np.sqrt(((source_xyz[:, None, :] - mics[None]) ** 2).sum(-1))
    return np.stack([(distance[:, j] - distance[:, i]) / SPEED for i, j in pairs], axis=1)


@settings(max_examples=40, deadline=None)
@given(st.floats(-30, 70), st.floats(-30, 60), st.integers(0, 2))
def test_the_true_position_explains_its_time_differences_whichever_candidate_holds_them(x, y, rank):
    site = site3()
    source = np.array([[x, y, 1.0]])
    exact = lags_s(source, site.mic_positions_m, site.mic_pairs)  # (1, P)
    candidates = np.full((1, len(site.mic_pairs), 3), 0.05)  # far-off decoys …
    candidates[:, :, rank] = exact  # … and the direct path at any rank
    misfit = candidate_misfit_m(source[:, :2], np.ones(1), site.mic_positions_m, np.array(site.mic_pairs), candidates, np.array([SPEED]))
    assert misfit[0] == pytest.approx(0.0, abs=1e-9)
    moved = candidate_misfit_m(
        source[:, :2] + 8.0, np.ones(1), site.mic_positions_m, np.array(site.mic_pairs), candidates, np.array([SPEED])
    )
    # 8 m off explains them worse: over this domain the smallest misfit is 0.109 m (at (−17, −30), found by
    # minimising it from a 41 × 37 grid of starts); far outside a 3-mic array a move can nearly keep every
    # range difference, so the bound is that, not metres
    assert moved[0] > 0.1


def test_a_pair_without_candidates_is_left_out_and_no_position_gives_nan():
    site = site3()
    source = np.array([[20.0, 10.0, 1.0], [np.nan, np.nan, 1.0]])
    candidates = lags_s(np.nan_to_num(source), site.mic_positions_m, site.mic_pairs)[..., None]
    candidates[0, 1, 0] = np.nan
    misfit = candidate_misfit_m(source[:, :2], np.ones(2), site.mic_positions_m, np.array(site.mic_pairs), candidates, np.full(2, SPEED))
    assert misfit[0] == pytest.approx(0.0, abs=1e-9) and np.isnan(misfit[1])


def measured_scene(n_positions: int = 60, per: int = 5, seed: int = 0) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Sources inside a 3-mic array whose GCC candidates hold the true lags (±20 µs) at rank 1 and a decoy at rank 2.

    The point model reads ``tdoa__hint_*`` (the truth ± 1 m); the solver's fixes are the truth ± 0.1 m.
    """
    rng = np.random.default_rng(seed)
    site = site3()
    n = n_positions * per
    position_id = np.repeat(np.arange(n_positions), per)
    source = np.column_stack([rng.uniform(5, 35, n_positions), rng.uniform(3, 30, n_positions)])[position_id]
    exact = lags_s(np.column_stack([source, np.ones(n)]), site.mic_positions_m, site.mic_pairs)
    solver = source + rng.normal(0, 0.1, (n, 2))
    features = pd.DataFrame(
        {
            "tdoa__hint_x_m": source[:, 0] + rng.normal(0, 1.0, n),
            "tdoa__hint_y_m": source[:, 1] + rng.normal(0, 1.0, n),
            col.SOLVER_X: solver[:, 0],
            col.SOLVER_Y: solver[:, 1],
            col.SOLVER_GDOP: np.ones(n),
            col.ENV_SPEED_OF_SOUND: np.full(n, SPEED),
        }
    )
    for p, (i, j) in enumerate(site.mic_pairs):
        features[col.tdoa_lag(i, j, 1)] = exact[:, p] + rng.normal(0, 2e-5, n)
        features[col.tdoa_lag(i, j, 2)] = rng.uniform(-0.1, 0.1, n)
    events = pd.DataFrame(
        {"event_id": np.arange(n), "position_id": position_id, "x_m": source[:, 0], "y_m": source[:, 1], "z_m": np.ones(n)}
    )
    return features, events


def test_a_model_estimate_that_explains_the_measurements_worse_is_never_substituted():
    """Every gate (here: always hand over) keeps the solver's fix where the model's estimate is far from what the lags say."""
    features, events = measured_scene()
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups < 50), np.flatnonzero(groups >= 50)
    # the test detections' model inputs point 15 m away (a site unlike the simulation) while their lags are right
    features.loc[test, "tdoa__hint_x_m"] += 15.0
    gate = ModelOnlyGate()
    out = LocalizationPipeline(components(gate, TrustSettings(novelty_factor=0))).fit_predict(features, events, train, test).predictions
    moved = out[col.error_m("model")] > 5
    assert moved.sum() >= 0.5 * len(out)  # the model's estimates did go wrong
    assert not out.loc[moved, col.SUBSTITUTED].any()
    assert (out.loc[moved, col.TRUST_REASON] == trust.REASON_EXPLAINS_WORSE).all()
    assert out.loc[moved, col.error_m("gate")].max() < 1.0  # … the solver's good fixes are reported there
    # accurate model estimates (the training-like detections) still pass
    same = LocalizationPipeline(components(gate, TrustSettings(novelty_factor=0)))
    features2, events2 = measured_scene(seed=1)
    kept = same.fit_predict(features2, events2, train, test).predictions
    assert kept[col.SUBSTITUTED].mean() >= 0.8


def test_without_a_solver_fix_a_model_estimate_that_explains_nothing_abstains():
    features, events = measured_scene()
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups < 50), np.flatnonzero(groups >= 50)
    features.loc[test, "tdoa__hint_x_m"] += 15.0
    features.loc[test, list(col.SOLVER_ESTIMATE_COLUMNS)] = np.nan
    parts = replace(components(ModelOnlyGate(), TrustSettings(novelty_factor=0)), point_model=HistGradientBoostingRegressor(max_iter=50))
    out = LocalizationPipeline(parts).fit_predict(features, events, train, test)
    p = out.predictions
    gross = p[col.error_m("model")] > 5
    assert gross.any()
    assert np.isinf(p.loc[gross, col.error_m("gate")]).all()  # no estimate: a failure, counted as an error
    assert (p.loc[gross, col.TRUST_REASON] == trust.REASON_ABSTAIN_MISFIT).all()


def test_the_check_can_be_turned_off_and_its_tolerance_is_reported():
    features, events = measured_scene()
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups < 50), np.flatnonzero(groups >= 50)
    features.loc[test, "tdoa__hint_x_m"] += 15.0
    off = TrustSettings(novelty_factor=0, handover_check=False, support_margin_m=100.0)
    out = LocalizationPipeline(components(ModelOnlyGate(), off)).fit_predict(features, events, train, test)
    assert out.predictions[col.SUBSTITUTED].all()
    on = LocalizationPipeline(components(ModelOnlyGate(), TrustSettings(novelty_factor=0))).fit_predict(features, events, train, test)
    tolerance = on.split_diagnostics[0]["trust"]["training_region"]["handover_tolerance_m"]
    assert 0 < tolerance < 5  # accurate (≤ 2 m) estimates misfit by at most a few metres of range difference


def test_outside_the_array_the_hand_over_admits_no_estimate_ten_metres_off():
    """The audit's grid on the lake's 3-mic array: exact time differences and two random decoys per pair, the solver's fix
    exact, every grid point a model estimate. Judged in position metres (misfit × GDOP) with the tolerance accurate
    estimates set, no point outside the array and 10 m or more from the source passes, for sources inside, 40 m south and
    85 m east; the range-metre RMS rule (1.8 m, the lake's) admitted hundreds at 85 m east. Inside the array a few ghosts,
    where decoys close the triangle, explain the lags as well as the source; the radius rule keeps the fix there (with the
    lake's median widest radius inside its array, 0.84 m in ``experiments/handover.py``'s own-simulation run)."""
    from acoustlab.method.trust import TrainingSupport, beyond_radius, misfit_excess_position_m
    from acoustlab.run.plugin_checks import compose_config
    from acoustlab.stages.sites import site_from_config
    from acoustlab.toolkit.geometry import gdop

    site = site_from_config(compose_config(["+site=frozen_lake"]).site)
    mics, pairs, height = site.mic_positions_m, np.array(site.mic_pairs), 1.5
    rng = np.random.default_rng(0)
    reach = np.hypot(*(mics[pairs[:, 1], :2] - mics[pairs[:, 0], :2]).T) / SPEED  # the largest lag of each pair, s

    def candidates(xy: np.ndarray) -> np.ndarray:
        decoys = rng.uniform(-1, 1, (len(xy), len(pairs), 2)) * reach[None, :, None]
        return np.concatenate([lags_s(np.column_stack([xy, np.full(len(xy), height)]), mics, site.mic_pairs)[..., None], decoys], -1)

    def misfit(xy: np.ndarray, cands: np.ndarray) -> np.ndarray:
        return candidate_misfit_m(xy, np.full(len(xy), height), mics, pairs, cands, np.full(len(xy), SPEED))

    def at_gdop(xy: np.ndarray) -> np.ndarray:
        return np.nan_to_num(gdop(mics, np.column_stack([xy, np.full(len(xy), height)])), nan=1e6, posinf=1e6)

    low, high = mics[:, :2].min(axis=0), mics[:, :2].max(axis=0)
    truth = np.column_stack([rng.uniform(low[0], high[0], 400), rng.uniform(low[1], high[1], 400)])
    accurate = truth + rng.normal(0, 0.7, truth.shape)  # out-of-fold estimates within a metre or two
    scaled = misfit(accurate, candidates(truth)) * at_gdop(accurate)
    tolerance = TrainingSupport(TrustSettings())._handover_tolerance(scaled, np.hypot(*(accurate - truth).T))
    assert 1.0 < tolerance < 5.0
    centre = mics[:, :2].mean(axis=0)
    xs, ys = np.meshgrid(np.arange(-150, 151, 2.0), np.arange(-150, 151, 2.0))
    for source in (centre + [5.0, 3.0], np.array([centre[0], low[1] - 40]), np.array([high[0] + 85, centre[1]])):
        cands = candidates(source[None])
        grid = source + np.column_stack([xs.ravel(), ys.ravel()])
        both = (misfit(source[None], cands).repeat(len(grid)), misfit(grid, cands.repeat(len(grid), axis=0)))
        passes = misfit_excess_position_m(both, at_gdop(grid), len(grid)) <= tolerance
        far = np.hypot(*(grid - source).T) >= 10.0
        outside = ((grid < low - 5) | (grid > high + 5)).any(axis=1)
        assert not (passes & far & outside).any()
        assert (passes & far).sum() <= 5  # inside the array a decoy can meet all three pairs at a few points
        assert passes[np.argmin(np.hypot(*(grid - source).T))]  # the truth itself passes
        handed = np.ones(len(grid), dtype=bool)
        overruled = beyond_radius(handed, grid, np.repeat(source[None], len(grid), 0), np.full((len(grid), 1), 0.84))
        assert not (passes & ~overruled & far).any()  # with the radius rule none 10 m or more off is reported


def test_a_model_estimate_farther_from_the_solver_fix_than_its_widest_radius_is_never_reported():
    """Without GCC candidates the misfit cannot judge a hand-over; the radius still does: a reported model estimate lies
    within the detection's widest radius of the solver's fix, the overruled rows report that fix with their reason, and
    deciding rows again gives what predicting them alone gives."""
    features, events = measured_scene()
    features = features.drop(columns=[c for c in features if c.startswith("tdoa__lag")])
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups < 50), np.flatnonzero(groups >= 50)
    features.loc[test[: len(test) // 2], "tdoa__hint_x_m"] += 15.0  # half the test detections' model inputs point 15 m away
    radii = [col.radius("fixed", level) for level in (0.5, 0.8, 0.95)]
    fitted = LocalizationPipeline(components(ModelOnlyGate(), TrustSettings(novelty_factor=0, support_margin_m=100.0))).fit(
        features, events, train
    )
    out, summary = fitted.predict(features.iloc[test], events.iloc[test])
    solver, reported = out[list(col.estimate_xy("solver"))].to_numpy(), out[list(col.estimate_xy("gate"))].to_numpy()
    apart = np.hypot(*(reported - solver).T)
    widest = out[radii].max(axis=1).to_numpy()
    overruled = (out[col.TRUST_REASON] == trust.REASON_BEYOND_RADIUS).to_numpy()
    assert overruled.sum() >= 0.3 * len(out)  # the misled model's estimates were caught …
    assert (apart[out[col.SUBSTITUTED].to_numpy()] <= widest[out[col.SUBSTITUTED].to_numpy()]).all()
    np.testing.assert_array_equal(reported[overruled], solver[overruled])  # … and the solver's fix reported there
    assert out[col.SUBSTITUTED].mean() >= 0.3  # the model's accurate estimates still pass
    assert summary["overridden"][trust.REASON_BEYOND_RADIUS] == overruled.sum()
    first, _ = fitted.predict(features.iloc[test[::2]], events.iloc[test[::2]])  # the rows alone give what they gave together
    pd.testing.assert_frame_equal(first.reset_index(drop=True), out.iloc[::2].reset_index(drop=True))
    off = LocalizationPipeline(
        components(ModelOnlyGate(), TrustSettings(novelty_factor=0, support_margin_m=100.0, handover_check=False))
    ).fit_predict(features, events, train, test)
    assert off.predictions[col.SUBSTITUTED].all()  # with the hand-over check off the rule is off too


def test_a_fix_its_residual_shows_wrong_keeps_the_gates_hand_over_however_far():
    """The radius rule trusts the solver's fix only where nothing shows it wrong: a redundant array's inconsistent fix (a
    gross error the gate is there to replace) leaves the hand-over standing; a fix the residual cannot judge does not."""
    solver = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [np.nan, np.nan]])
    model = np.array([[12.0, 0.0], [12.0, 0.0], [3.0, 0.0], [12.0, 0.0]])
    radii = np.array([[2.0, 5.0, np.inf], [2.0, 5.0, np.inf], [2.0, 5.0, np.inf], [2.0, 5.0, 8.0]])
    wrong = np.array([False, True, False, False])
    assert trust.beyond_radius(np.ones(4, dtype=bool), model, solver, radii, wrong).tolist() == [True, False, False, False]
    assert not trust.beyond_radius(np.zeros(4, dtype=bool), model, solver, radii).any()  # no hand-over, nothing to undo
