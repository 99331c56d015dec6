"""The point model is only trusted where it has seen data; positions never mix estimates; radii stay bounded."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from sklearn.neighbors import KNeighborsRegressor

from acoustlab.core import columns as col
from acoustlab.core.contracts import GateDecision
from acoustlab.core.errors import ConfigError
from acoustlab.method import trust
from acoustlab.method.pipeline import Components, LocalizationPipeline
from acoustlab.method.trust import TrainingSupport, TrustSettings, apply_trust
from acoustlab.reporting.positions import positions_table
from plugins.conformal.split import SplitConformal
from plugins.gates.bounding_box import BoundingBoxGate
from plugins.gates.learned import LearnedGate
from tests.test_pipeline_calibration import ExactMedian, site3


def scene(n_positions: int = 100, per: int = 5, seed: int = 0, outside: int = 0) -> tuple[pd.DataFrame, pd.DataFrame]:
    """A 3-mic-like scene with redundant TDOAs: good fixes have small residuals, 20 % gross fixes large ones.

    With ``outside`` > 0 the last ``outside`` positions are sources 15–25 m outside the training
    region (east of the array) with exact, consistent solver fixes.
    """
    rng = np.random.default_rng(seed)
    n = n_positions * per
    position_id = np.repeat(np.arange(n_positions), per)
    source = np.column_stack([rng.uniform(2, 38, n_positions), rng.uniform(2, 33, n_positions)])
    if outside:
        source[-outside:] = np.column_stack([rng.uniform(55, 65, outside), rng.uniform(5, 30, outside)])
    source = source[position_id]
    solver = source + rng.normal(0, 0.1, (n, 2))
    residual = np.abs(rng.normal(0, 1e-5, n))
    gross = (rng.random(n) < 0.2) & (source[:, 0] < 50)
    solver[gross] += rng.uniform(6, 15, (gross.sum(), 2)) * rng.choice([-1, 1], (gross.sum(), 2))
    residual[gross] = rng.uniform(5e-4, 2e-3, gross.sum())
    features = pd.DataFrame({
        "tdoa__hint_x_m": source[:, 0] + rng.normal(0, 2.0, n),
        "tdoa__hint_y_m": source[:, 1] + rng.normal(0, 2.0, n),
        col.SOLVER_X: solver[:, 0],
        col.SOLVER_Y: solver[:, 1],
        col.solver_column("residual_s"): residual,
        col.SOLVER_GDOP: np.ones(n),
    })
    events = pd.DataFrame({"event_id": np.arange(n), "position_id": position_id, "x_m": source[:, 0], "y_m": source[:, 1],
                           "z_m": np.full(n, 1.0)})
    return features, events


def components(gate, settings: TrustSettings | None = None) -> Components:
    return Components(site=site3(), feature_sets={}, solver=None, point_model=KNeighborsRegressor(n_neighbors=10), gate=gate,
                      error_model=ExactMedian(), scorers={"fixed": SplitConformal()}, levels=[0.5, 0.8, 0.95], calibration_folds=5,
                      trust=settings or TrustSettings())


def test_consistent_solver_fix_outside_the_training_region_is_kept():
    """A speaker 15–25 m outside the array: the box gate would hand over to the model; the solver's exact fix is kept."""
    features, events = scene(outside=10)
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups < 90), np.flatnonzero(groups >= 90)
    out = LocalizationPipeline(components(BoundingBoxGate())).fit_predict(features, events, train, test).predictions
    assert out["substituted"].sum() == 0
    np.testing.assert_allclose(out[list(col.estimate_xy("gate"))].to_numpy(), out[list(col.estimate_xy("solver"))].to_numpy())
    assert out[col.error_m("gate")].max() < 1.0
    assert (out[col.TRUST_REASON] != "").all()
    assert out[col.trust_flag("solver_outside_support")].all()
    # … where without the trust check the model's extrapolated guess replaced every one of them
    plain = LocalizationPipeline(components(BoundingBoxGate(), TrustSettings(enabled=False))).fit_predict(features, events, train, test).predictions
    assert plain["substituted"].all() and plain[col.error_m("gate")].min() > 10


def test_inside_the_training_region_the_gate_decides_as_before():
    """On events like the training ones the trust check overrides almost nothing."""
    features, events = scene(seed=1)
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups % 5 != 0), np.flatnonzero(groups % 5 == 0)
    gate = LearnedGate(seed=0, n_threads=1, stakes_cap_m=None)
    trusted = LocalizationPipeline(components(gate)).fit_predict(features, events, train, test).predictions
    plain = LocalizationPipeline(components(gate, TrustSettings(enabled=False))).fit_predict(features, events, train, test).predictions
    assert (trusted[col.TRUST_REASON] != "").mean() <= 0.05
    assert trusted[col.error_m("gate")].quantile(0.95) <= plain[col.error_m("gate")].quantile(0.95) * 1.05


def _support(features: pd.DataFrame, events: pd.DataFrame, settings: TrustSettings | None = None) -> TrainingSupport:
    truth = events[["x_m", "y_m", "z_m"]].to_numpy(float)
    error = np.hypot(*(features[list(col.SOLVER_ESTIMATE_COLUMNS)].to_numpy() - truth[:, :2]).T)
    return TrainingSupport(settings or TrustSettings()).fit(features, truth, error, events["position_id"].to_numpy())


def test_a_model_asked_outside_its_training_support_is_not_used():
    features, events = scene()
    support = _support(features, events)
    novel = features.iloc[:3].copy()
    novel["tdoa__hint_x_m"] = 400.0  # nothing like any training row
    solver_xy = np.array([[10.0, 10.0], [np.nan, np.nan], [20.0, 20.0]])
    model_xy = np.array([[11.0, 11.0], [12.0, 12.0], [21.0, 21.0]])
    novel[list(col.SOLVER_ESTIMATE_COLUMNS)] = solver_xy
    substituted = np.ones(3, dtype=bool)
    out = apply_trust(GateDecision(model_xy.copy(), substituted), solver_xy, model_xy, novel, novel, support)
    assert (out.flags["novelty"] > 1).all()
    np.testing.assert_array_equal(out.decision.position_m[[0, 2]], solver_xy[[0, 2]])  # the solver's fix kept
    assert np.isnan(out.decision.position_m[1]).all()  # no solver fix: the method abstains …
    assert out.reason[1] == trust.REASON_ABSTAIN and out.reason[0] == trust.REASON_NOVEL  # … and says why
    assert not out.decision.substituted.any()
    # a row like the training ones: the gate's choice stands
    same = apply_trust(GateDecision(model_xy[:1].copy(), substituted[:1]), solver_xy[:1], model_xy[:1], features.iloc[:1],
                       features.iloc[:1], support)
    assert same.decision.substituted.all() and same.reason[0] == trust.REASON_GATE


def test_height_outside_the_training_range_is_outside_the_support():
    """A 3-D fix 100 m up where the site simulated 1 m: outside, whatever its horizontal position."""
    features, events = scene()
    support = _support(features, events)
    xy = np.array([[20.0, 15.0], [20.0, 15.0]])
    assert support.outside_region(xy, np.array([100.0, 1.5])).tolist() == [True, False]
    assert support.outside_region(np.array([[20.0, 15.0], [80.0, 15.0], [np.nan, np.nan]])).tolist() == [False, True, False]


def test_without_redundant_measurements_no_fix_counts_as_consistent():
    """3 mics in 2-D fit any fix exactly (residual 0): consistency cannot be shown, so the residual rule is off."""
    features, events = scene()
    features[col.solver_column("residual_s")] = 0.0
    support = _support(features, events)
    assert support.residual_limit_s_ is None and not support.consistent(features).any()


def test_trust_settings_are_checked():
    with pytest.raises(ConfigError, match="support_margin_m"):
        TrustSettings(support_margin_m=-1)
    with pytest.raises(ConfigError, match="novelty_quantile"):
        TrustSettings(novelty_quantile=0)


def test_learned_gate_with_one_class_almost_absent_falls_back_to_the_solver():
    """Where the solver is (almost) never worse than the model the classifier has nothing to learn: keep the solver."""
    rng = np.random.default_rng(0)
    features, events = scene()
    truth = events[["x_m", "y_m"]].to_numpy()
    solver = truth + rng.normal(0, 0.01, truth.shape)
    model = truth + rng.normal(0, 3.0, truth.shape)
    features[list(col.SOLVER_ESTIMATE_COLUMNS)] = solver
    gate = LearnedGate(seed=0, n_threads=1).fit(solver, model, features, site3(), truth, groups=events["position_id"].to_numpy())
    assert gate.diagnostics()["fallback"]
    decision = gate.decide(solver, model, features, site3())
    np.testing.assert_array_equal(decision.position_m, solver)


def test_learned_gate_with_a_useless_classifier_falls_back():
    """Labels the cues cannot predict (out-of-fold AUC near 0.5 or below): the gate keeps the solver's fix."""
    rng = np.random.default_rng(2)
    features, events = scene()
    truth = events[["x_m", "y_m"]].to_numpy()
    solver = truth + rng.normal(0, 1.0, truth.shape)  # solver and model equally good, independent of every cue
    model = truth + rng.normal(0, 1.0, truth.shape)
    features[list(col.SOLVER_ESTIMATE_COLUMNS)] = solver
    gate = LearnedGate(seed=0, n_threads=1, min_auc=0.75).fit(solver, model, features, site3(), truth, groups=events["position_id"].to_numpy())
    assert "AUC" in gate.diagnostics()["fallback"]
    assert not gate.decide(solver, model, features, site3()).substituted.any()


def test_singular_geometry_gives_a_bounded_gdop_scaled_radius():
    rng = np.random.default_rng(0)
    error, predicted, gdop = rng.lognormal(size=500), rng.uniform(0.5, 2, 500), rng.uniform(1, 5, 500)
    scorer = SplitConformal("gdop").fit(error, predicted, gdop, [0.5, 0.95])
    radius = scorer.radius(np.array([1.0, 1.0]), np.array([np.quantile(gdop, 0.99), 1e6]))
    assert np.isfinite(radius).all()
    np.testing.assert_allclose(radius[1], radius[0])  # capped at the calibration 99th percentile
    uncapped = SplitConformal("gdop", gdop_cap_quantile=None).fit(error, predicted, gdop, [0.5, 0.95])
    assert uncapped.radius(np.array([1.0]), np.array([1e6]))[0, 1] > 1e4 * radius[1, 1]


def test_no_positions_row_mixes_estimates():
    """x, y, z of a row come from one estimate: the model's x, y never carry the solver's height."""
    predictions = pd.DataFrame({
        "event_id": [0, 1, 2], "substituted": [False, True, False],
        "solver_x_m": [1.0, 2.0, np.nan], "solver_y_m": [1.0, 2.0, np.nan], "model_x_m": [5.0, 6.0, 7.0], "model_y_m": [5.0, 6.0, 7.0],
        "gate_x_m": [1.0, 6.0, np.nan], "gate_y_m": [1.0, 6.0, np.nan], col.SOLVER_SOURCE_HEIGHT: [100.0, 90.0, np.nan],
        "predicted_error_m": [1.0, 1.0, 1.0], col.radius("fixed", 0.95): [2.0, 2.0, 2.0],
        col.TRUST_REASON: ["", "", trust.REASON_ABSTAIN],
    })
    table = positions_table(predictions, [0.95], ["fixed"])
    assert table["z_m"].iloc[0] == 100.0 and np.isnan(table["z_m"].iloc[1])
    assert table["source"].tolist() == ["solver", "model", "none"]
    assert table["solver_z_m"].iloc[1] == 90.0
    np.testing.assert_allclose(table["solver_model_distance_m"].iloc[:2], [np.hypot(4, 4)] * 2)
    assert table["abstain_reason"].iloc[2] == trust.REASON_ABSTAIN and not table["placed"].iloc[2]
