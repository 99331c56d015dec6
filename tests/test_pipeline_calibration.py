"""The pipeline's calibration is out-of-sample at every level, and the error model sees the gate's context."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.stats import spearmanr
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.ensemble import HistGradientBoostingRegressor
from sklearn.neighbors import KNeighborsRegressor

from acoustlab.core import columns as col
from acoustlab.core.contracts import GateDecision
from acoustlab.core.errors import DataError
from acoustlab.core.types import NoiseRegime, Site
from acoustlab.method.pipeline import Components, LocalizationPipeline
from plugins.conformal.split import SplitConformal
from plugins.gates.learned import LearnedGate


def site3() -> Site:
    return Site(
        "t",
        np.array([[0.0, 0, 1], [40, 0, 1], [20, 35, 1]]),
        np.zeros((0, 2)),
        np.zeros(0),
        (10, 10),
        (50, 50),
        "x",
        100.0,
        "rigid",
        None,
        (NoiseRegime("white"),),
        (10, 10),
        ("synthetic",),
        (1.0, 1.0),
        0.2,
    )


def scene(n_positions: int = 120, per: int = 5, seed: int = 0) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Events whose solver is exact but for 20 % gross fixes that no feature reveals.

    The features carry the truth with noise (so the point model learns a 2 m estimate) and an
    uninformative diagnostic; only the distance between the solver's and the model's estimates
    tells a gross fix from a good one.
    """
    rng = np.random.default_rng(seed)
    n = n_positions * per
    position_id = np.repeat(np.arange(n_positions), per)
    source = np.column_stack([rng.uniform(2, 38, n_positions), rng.uniform(2, 33, n_positions)])[position_id]
    solver = source + rng.normal(0, 0.1, (n, 2))
    gross = rng.random(n) < 0.2
    solver[gross] += rng.uniform(6, 15, (gross.sum(), 2)) * rng.choice([-1, 1], (gross.sum(), 2))
    features = pd.DataFrame(
        {
            "tdoa__hint_x_m": source[:, 0] + rng.normal(0, 2.0, n),
            "tdoa__hint_y_m": source[:, 1] + rng.normal(0, 2.0, n),
            "tdoa__noise": rng.normal(size=n),
            col.SOLVER_X: solver[:, 0],
            col.SOLVER_Y: solver[:, 1],
            col.SOLVER_GDOP: np.ones(n),
        }
    )
    events = pd.DataFrame({"event_id": np.arange(n), "position_id": position_id, "x_m": source[:, 0], "y_m": source[:, 1]})
    return features, events


class RecordingGate(BaseEstimator):
    """A gate that keeps the solver's fix and remembers which positions it was fitted on and asked about."""

    required_feature_groups: tuple[str, ...] = ()
    log: list[tuple[set, set]] = []

    def fit(self, solver_position_m, model_position_m, features, site, truth_m, groups=None):
        self.fitted_on_ = set(np.unique(groups))
        return self

    def decide(self, solver_position_m, model_position_m, features, site):
        RecordingGate.log.append((self.fitted_on_, set(features.index)))
        return GateDecision(solver_position_m.copy(), np.zeros(len(solver_position_m), dtype=bool))

    def diagnostics(self):
        return {}


class ExactMedian(BaseEstimator, RegressorMixin):
    """Error model stand-in that predicts the median of its training errors (keeps the test about the gate)."""

    def fit(self, x, y):
        self.value_ = float(np.median(y))
        return self

    def predict(self, x):
        return np.full(len(x), self.value_)


def components(gate, error_model, cues: bool) -> Components:
    return Components(
        site=site3(),
        feature_sets={},
        solver=None,
        point_model=KNeighborsRegressor(n_neighbors=10),
        gate=gate,
        error_model=error_model,
        scorers={"fixed": SplitConformal()},
        levels=[0.5, 0.8, 0.95],
        calibration_folds=5,
        error_model_gate_cues=cues,
    )


def test_calibration_gates_never_decide_on_a_position_they_were_fitted_on():
    """Every gate decision (calibration and test) is about positions the deciding gate never saw in training."""
    features, events = scene()
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups >= 20), np.flatnonzero(groups < 20)
    RecordingGate.log = []
    LocalizationPipeline(components(RecordingGate(), ExactMedian(), cues=True)).fit_predict(features, events, train, test)
    assert len(RecordingGate.log) == 6  # one gate per calibration fold, then the final gate on the test rows
    for fitted_on, rows in RecordingGate.log:
        asked = set(groups[sorted(rows)])
        assert fitted_on and not (fitted_on & asked)
    decided = set().union(*(rows for _, rows in RecordingGate.log[:5]))
    assert decided == set(train)  # every training event got exactly its out-of-fold decision


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_gate_context_lets_the_error_model_rank_gross_fixes(seed):
    """Where only solver–model disagreement reveals a gross fix, the gate's context raises the error model's ρ."""
    features, events = scene(seed=seed)
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups % 4 != 0), np.flatnonzero(groups % 4 == 0)
    rho = {}
    for cues in (False, True):
        error_model = HistGradientBoostingRegressor(loss="quantile", quantile=0.5, max_iter=100, random_state=0)
        gate = LearnedGate(seed=0, n_threads=1, p50_tolerance=0.0, stakes_cap_m=None)  # the unweighted gate this scene was built for
        out = LocalizationPipeline(components(gate, error_model, cues)).fit_predict(features, events, train, test).predictions
        rho[cues] = spearmanr(out["predicted_error_m"], out[col.error_m("gate")]).statistic
    assert rho[True] > rho[False] + 0.2, rho
    assert rho[True] > 0.5, rho


def test_gate_context_columns_reach_the_error_model_only_when_asked():
    features, events = scene(40)
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups >= 8), np.flatnonzero(groups < 8)
    seen: dict[bool, list[str]] = {}

    class Spy(ExactMedian):
        def fit(self, x, y):
            seen[cues] = list(x.columns)
            return super().fit(x, y)

    for cues in (False, True):
        LocalizationPipeline(components(RecordingGate(), Spy(), cues)).fit_predict(features, events, train, test)
    gate_columns = [col.GATE_SOLVER_MODEL_DISTANCE, col.GATE_SUBSTITUTED, col.GATE_ESTIMATE_GDOP, col.GATE_ESTIMATE_RANGE]
    assert not set(gate_columns) & set(seen[False])
    assert set(gate_columns) <= set(seen[True])
    assert col.SOLVER_X not in seen[True]  # the error model still never sees the solver's point estimate


def shifted_scene(seed: int = 0) -> tuple[pd.DataFrame, pd.DataFrame, np.ndarray, np.ndarray]:
    """Simulated positions 0–79 with 0.1 m solver noise; field positions 80–119 with 1 m (a simulation-to-field shift)."""
    features, events = scene(120, seed=seed)
    rng = np.random.default_rng(seed + 10)
    field = events["position_id"].to_numpy() >= 80
    features.loc[field, [col.SOLVER_X, col.SOLVER_Y]] = events.loc[field, ["x_m", "y_m"]].to_numpy() + rng.normal(0, 1.0, (field.sum(), 2))
    features.loc[~field, [col.SOLVER_X, col.SOLVER_Y]] = events.loc[~field, ["x_m", "y_m"]].to_numpy() + rng.normal(
        0, 0.1, ((~field).sum(), 2)
    )
    events["is_field"] = field
    groups = events["position_id"].to_numpy()
    return features, events, np.flatnonzero(groups < 110), np.flatnonzero(groups >= 110)


@pytest.mark.parametrize("mode, covers", [("all", False), ("auto", True), ("field", True)])
def test_field_rows_calibrate_where_simulation_is_not_exchangeable_with_the_field(mode, covers):
    features, events, train, test = shifted_scene()
    c = components(RecordingGate(), ExactMedian(), cues=False)
    c.calibrate_on = mode
    result = LocalizationPipeline(c).fit_predict(features, events, train, test)
    out = result.predictions
    coverage = (out[col.error_m("gate")] <= out[col.radius("fixed", 0.8)]).mean()
    assert (0.65 <= coverage <= 0.95) if covers else coverage < 0.4, coverage
    info = result.split_diagnostics[0]["calibration"]
    assert info["on"] == ("all" if mode == "all" else "field")
    assert info["n_positions"] == (110 if mode == "all" else 30)


def test_calibration_on_the_field_needs_field_rows():
    features, events, train, test = shifted_scene()
    events["is_field"] = False
    c = components(RecordingGate(), ExactMedian(), cues=False)
    c.calibrate_on = "field"
    with pytest.raises(DataError, match="calibrate_on=field"):
        LocalizationPipeline(c).fit_predict(features, events, train, test)
    c.calibrate_on = "auto"  # falls back to every training row
    result = LocalizationPipeline(c).fit_predict(features, events, train, test)
    assert result.split_diagnostics[0]["calibration"]["on"] == "all"


class LimitedKnn(KNeighborsRegressor):
    """A point model with its own row limit (as TabPFN declares one) that records the rows of every fit."""

    fits: list[pd.Index] = []

    def __init__(self, n_neighbors=10, max_train_rows=None):
        super().__init__(n_neighbors=n_neighbors)
        self.max_train_rows = max_train_rows

    def fit(self, x, y):
        LimitedKnn.fits.append(x.index)
        return super().fit(x, y)


class LimitedMedian(ExactMedian):
    """The error model's stand-in with a row limit, recording the rows of every fit."""

    fits: list[pd.Index] = []

    def __init__(self, max_train_rows=None):
        self.max_train_rows = max_train_rows

    def fit(self, x, y):
        LimitedMedian.fits.append(x.index)
        return super().fit(x, y)


@pytest.mark.parametrize("limit", [None, 150])
def test_a_model_with_its_own_row_limit_fits_on_whole_positions_within_it(limit):
    """One protocol budget, several models: a model's ``max_train_rows`` caps its own fits (whole positions, from the seed)."""
    features, events = scene(120)
    groups = events["position_id"].to_numpy()
    train, test = np.flatnonzero(groups >= 20), np.flatnonzero(groups < 20)  # 500 training rows
    runs = []
    for _ in range(2):
        LimitedKnn.fits, LimitedMedian.fits = [], []
        c = components(RecordingGate(), LimitedMedian(max_train_rows=limit), cues=False)
        c.point_model = LimitedKnn(max_train_rows=limit)
        out = LocalizationPipeline(c).fit_predict(features, events, train, test).predictions
        runs.append((out, [list(i) for i in LimitedKnn.fits + LimitedMedian.fits]))
    fits = LimitedKnn.fits + LimitedMedian.fits
    assert len(LimitedKnn.fits) == 12 and len(LimitedMedian.fits) == 6  # x and y per fold and final; error model per fold and final
    sizes = [len(i) for i in fits]
    if limit is None:
        assert max(sizes) == 500
    else:
        assert max(sizes) <= limit and min(sizes) >= limit - 5  # 5 events per position: whole positions fill the limit
        for rows in fits:
            kept = set(groups[rows])
            assert all((groups[train] == g).sum() == (groups[rows] == g).sum() for g in kept)  # never part of a position
    assert runs[0][1] == runs[1][1]  # the same rows from the same seed
    pd.testing.assert_frame_equal(runs[0][0], runs[1][0])


def test_a_neighbours_model_is_clipped_to_the_rows_it_is_fitted_on(caplog):
    """model=knn (n_neighbors=10) on a calibration fold with 6 rows: clipped with a warning, not a scikit-learn traceback."""
    import logging

    from sklearn.neighbors import KNeighborsRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    from acoustlab.method.pipeline import clone_for_rows

    configured = make_pipeline(StandardScaler(), KNeighborsRegressor(n_neighbors=10))
    caplog.set_level(logging.WARNING)
    model = clone_for_rows(configured, 6).fit(np.arange(12.0).reshape(6, 2), np.arange(6.0))
    assert model.predict(np.zeros((3, 2))).shape == (3,)
    assert configured.get_params()["kneighborsregressor__n_neighbors"] == 10  # the configured model is untouched
    assert any("kneighborsregressor__n_neighbors=10 > 6 training rows" in r.message for r in caplog.records)
    assert clone_for_rows(configured, 50).get_params()["kneighborsregressor__n_neighbors"] == 10
