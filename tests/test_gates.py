"""Gates: τ* selection rule on a constructed case with a known answer, decisions, contracts."""

import numpy as np
import pandas as pd
import pytest

from acoustlab.core.errors import ConfigError
from acoustlab.core.types import NoiseRegime, Site
from plugins.gates.hybrid import HybridGate, select_tau
from plugins.gates.simple import ModelOnlyGate, SolverOnlyGate


def test_select_tau_known_answer():
    solver = np.concatenate([np.full(95, 1.0), np.full(5, 100.0)])  # p50 1, p99 100
    taus = np.array([1.0, 2.0, 3.0, 4.0])
    gated = np.stack(
        [
            np.concatenate([np.full(95, 1.5), np.full(5, 5.0)]),  # τ=1: p99 ok but median +50 % → rejected
            np.concatenate([np.full(95, 1.1), np.full(5, 10.0)]),  # τ=2: ok (p99 ≤ 33, median +10 %)
            np.concatenate([np.full(95, 1.0), np.full(5, 30.0)]),  # τ=3: ok → the most permissive acceptable
            np.concatenate([np.full(95, 1.0), np.full(5, 60.0)]),  # τ=4: p99 too high → rejected
        ]
    )
    tau, grid, met = select_tau(solver, gated, taus)
    assert met and tau == 3.0
    assert list(grid.columns) == ["tau_db", "p50_m", "p99_m"]
    tau, _, met = select_tau(solver, gated[[3]], taus[[3]])
    assert not met and tau == 4.0  # fallback: lowest p99 within the median tolerance


def site3():
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


def test_hybrid_gate_uses_box_then_energy():
    site = site3()
    truth = np.array([[20.0, 10.0], [10.0, 5.0], [25.0, 20.0]])
    d = np.sqrt(((np.column_stack([truth, np.ones(3)])[:, None] - site.mic_positions_m[None]) ** 2).sum(-1))
    levels = -20 * np.log10(d)
    solver = truth.copy()
    solver[1] = [500.0, 500.0]  # outside the box
    solver[2] = [2.0, 30.0]  # inside the box, but the levels say otherwise
    feats = pd.DataFrame({f"environment__level_{m}_db": levels[:, m] for m in range(3)})
    model = truth + 0.5
    decision = HybridGate(tau_db=1.0).decide(solver, model, feats, site)
    assert decision.substituted.tolist() == [False, True, True]
    np.testing.assert_allclose(decision.position_m[0], truth[0])


def test_simple_gates():
    s = np.array([[1.0, 1.0], [np.nan, np.nan]])
    m = np.array([[2.0, 2.0], [3.0, 3.0]])
    assert SolverOnlyGate().decide(s, m, pd.DataFrame(index=range(2)), site3()).substituted.tolist() == [False, True]
    assert ModelOnlyGate().decide(s, m, pd.DataFrame(index=range(2)), site3()).substituted.all()


def test_hybrid_gate_without_tau_or_levels_is_explained():
    from acoustlab.core.errors import DataError

    with pytest.raises(DataError, match="no τ"):
        HybridGate().decide(np.zeros((1, 2)), np.zeros((1, 2)), pd.DataFrame(index=[0]), site3())
    with pytest.raises(DataError, match="environment"):
        HybridGate(tau_db=3.0).decide(np.full((1, 2), 10.0), np.zeros((1, 2)), pd.DataFrame(index=[0]), site3())


def gate_scene(n=400, seed=0):
    """Events on site3 where the solver is exact except for gross fixes; diverged fixes lie far outside the box.

    Returns solver, model, truth, features (levels, solver diagnostics), groups and the gross mask.
    """
    rng = np.random.default_rng(seed)
    site = site3()
    truth = np.column_stack([rng.uniform(0, 40, n), rng.uniform(0, 35, n)])
    d = np.sqrt(((np.column_stack([truth, np.ones(n)])[:, None] - site.mic_positions_m[None]) ** 2).sum(-1))
    levels = -20 * np.log10(d) + rng.normal(0, 1.0, (n, 3))
    solver = truth + rng.normal(0, 0.2, (n, 2))
    gross = rng.random(n) < 0.25
    solver[gross] = truth[gross] + rng.uniform(8, 20, (gross.sum(), 2)) * rng.choice([-1, 1], (gross.sum(), 2))
    diverged = rng.random(n) < 0.03
    solver[diverged] = 1e5
    model = truth + rng.normal(0, 2.0, (n, 2))
    residual = np.where(gross, rng.uniform(0.5, 2.0, n), rng.uniform(0.0, 0.6, n))  # an informative solver diagnostic
    features = pd.DataFrame(
        {
            **{f"environment__level_{m}_db": levels[:, m] for m in range(3)},
            "solver__residual_m": residual,
            "solver__x_m": solver[:, 0],
            "solver__y_m": solver[:, 1],
        }
    )
    return site, solver, model, truth, features, np.arange(n) // 5, gross


def test_tau_is_chosen_against_the_box_gated_solver():
    """The box alone removes the diverged fixes and so would meet the old rule ('3× lower p99 than the bare solver') at any τ;
    against the box-gated solver the most permissive τ (no energy substitution at all) must not win."""
    site, solver, model, truth, features, groups, _ = gate_scene()
    bare = np.sqrt(((solver - truth) ** 2).sum(1))
    gate = HybridGate().fit(solver, model, features, site, truth, groups=groups)
    top = gate.tau_grid_["tau_db"].max()
    box_only = gate.tau_grid_.loc[gate.tau_grid_["tau_db"] == top, "p99_m"].iloc[0]
    assert box_only * 3 <= np.percentile(bare, 99)  # the old rule would pass on the box alone …
    assert gate.tau_ < top  # … the fixed rule does not let it
    assert len(gate.tau_grid_) > 5 and gate.tau_grid_["tau_db"].is_monotonic_increasing  # a grid from the data


@pytest.mark.slow
def test_learned_gate_reaches_the_oracle_on_an_informative_diagnostic():
    from plugins.gates.learned import LearnedGate

    site, solver, model, truth, features, groups, gross = gate_scene(600)
    train, test = groups < 80, groups >= 80
    gate = LearnedGate(seed=0).fit(solver[train], model[train], features[train], site, truth[train], groups=groups[train])
    decision = gate.decide(solver[test], model[test], features[test], site)
    err = np.sqrt(((decision.position_m - truth[test]) ** 2).sum(1))
    oracle = np.minimum(np.sqrt(((solver[test] - truth[test]) ** 2).sum(1)), np.sqrt(((model[test] - truth[test]) ** 2).sum(1)))
    assert gate.diagnostics()["oof_auc"] > 0.95
    assert np.percentile(err, 95) <= 1.2 * np.percentile(oracle, 95)
    assert decision.substituted[gross[test]].mean() > 0.9 and decision.substituted[~gross[test]].mean() < 0.2
    # a gate fitted for real (not a fall-back) is saved without pickle and decides the same once loaded
    import tempfile
    from pathlib import Path

    from acoustlab.method.saved import load_method, save_method

    with tempfile.TemporaryDirectory() as folder:
        loaded = load_method(Path(folder), save_method(gate, Path(folder), "gate"))
    again = loaded.decide(solver[test], model[test], features[test], site)
    np.testing.assert_array_equal(again.position_m, decision.position_m)
    assert loaded.diagnostics()["threshold_grid"] == gate.diagnostics()["threshold_grid"]


def test_learned_gate_never_trains_on_a_held_out_position(monkeypatch):
    """Every out-of-fold probability comes from a classifier fitted without that position's events."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    from plugins.gates.learned import LearnedGate

    site, solver, model, truth, features, groups, _ = gate_scene(300)
    seen: list[pd.Index] = []
    original = HistGradientBoostingClassifier.fit

    def spy(self, x, y, **kw):
        seen.append(x.index)
        return original(self, x, y, **kw)

    monkeypatch.setattr(HistGradientBoostingClassifier, "fit", spy)
    LearnedGate(n_folds=4).fit(solver, model, features, site, truth, groups=groups)
    assert len(seen) == 5  # 4 out-of-fold fits, then the final one
    fold_positions = [set(groups[idx]) for idx in seen[:4]]
    held = [set(np.unique(groups)) - s for s in fold_positions]
    assert all(h and not (h & s) for h, s in zip(held, fold_positions, strict=True))
    assert set().union(*held) >= set(np.unique(groups[np.isfinite(solver).all(1) & (np.abs(solver) < 1e4).all(1)]))


@pytest.mark.slow
def test_learned_gate_survives_a_cue_missing_in_a_whole_fold():
    """A diagnostic present for only a few positions (e.g. a 3-D height GDOP) must not break the out-of-fold fits."""
    from plugins.gates.learned import LearnedGate

    site, solver, model, truth, features, groups, _ = gate_scene(400)
    rare = np.full(len(features), np.nan)
    rare[groups == 3] = 1.0  # one position only: every fold but one trains without it
    features = features.assign(solver__height_gdop=rare)
    gate = LearnedGate(n_folds=5).fit(solver, model, features, site, truth, groups=groups)
    assert gate.decide(solver, model, features, site).position_m.shape == solver.shape


def test_learned_gate_weighs_events_by_what_a_wrong_choice_costs(monkeypatch):
    """With stakes_cap_m every classifier fit gets |solver error − model error| (capped) as sample weights."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    from plugins.gates.learned import LearnedGate

    site, solver, model, truth, features, groups, _ = gate_scene(300)
    weights: list = []
    original = HistGradientBoostingClassifier.fit

    def spy(self, x, y, sample_weight=None):
        weights.append(sample_weight)
        return original(self, x, y, sample_weight=sample_weight)

    monkeypatch.setattr(HistGradientBoostingClassifier, "fit", spy)
    LearnedGate(n_folds=3, stakes_cap_m=5.0).fit(solver, model, features, site, truth, groups=groups)
    final = weights[-1]
    stakes = np.abs(np.sqrt(((solver - truth) ** 2).sum(1)) - np.sqrt(((model - truth) ** 2).sum(1)))
    inside = ~LearnedGate()._failed(solver, site)  # failures are substituted, never trained on
    assert final == pytest.approx(np.clip(stakes[inside], 1e-3, 5.0))
    assert final.max() == 5.0 and final.min() < 1.0
    LearnedGate(n_folds=3, stakes_cap_m=None).fit(solver, model, features, site, truth, groups=groups)
    assert weights[-1] is None  # unweighted on request (the default caps at 20 m, as conf/gate/learned.yaml)
    with pytest.raises(ConfigError, match="stakes_cap_m"):
        LearnedGate(stakes_cap_m=0)
