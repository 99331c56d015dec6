"""The cross-fit protocol: every event predicted once, positions never in training and test together."""

import numpy as np
import pandas as pd
import pytest

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.method import trust
from acoustlab.method.protocols.cross_fit import CrossFitProtocol
from acoustlab.reporting.metrics import position_bootstrap_ci
from acoustlab.run.app import run_experiment


def events(n_positions=37, per=5):
    return pd.DataFrame({"event_id": np.arange(n_positions * per), "position_id": np.repeat(np.arange(n_positions), per)})


@pytest.mark.parametrize("cap", [1000, 60])
def test_every_event_is_predicted_once_and_no_position_is_on_both_sides(cap):
    ev = events()
    splits = CrossFitProtocol(n_folds=6, max_train_rows=cap, seed=3).splits(ev)
    tests = np.concatenate([t for _, t in splits])
    assert np.array_equal(np.sort(tests), np.arange(len(ev)))  # a partition: each event exactly once
    groups = ev["position_id"].to_numpy()
    for train, test in splits:
        assert not set(groups[train]) & set(groups[test])
        assert train.size <= cap
        assert all((groups[train] == g).sum() == 5 for g in np.unique(groups[train]))  # whole positions
    # the fold assignment depends on the seed, not on position-id order
    other = CrossFitProtocol(n_folds=6, max_train_rows=cap, seed=4).splits(ev)
    assert any(not np.array_equal(a[1], b[1]) for a, b in zip(splits, other, strict=True))


def test_bad_settings_are_named():
    with pytest.raises(ConfigError, match="n_folds"):
        CrossFitProtocol(n_folds=1)
    with pytest.raises(DataError, match="at least 10 source positions"):
        CrossFitProtocol(n_folds=10).splits(events(n_positions=4))


def test_position_bootstrap_interval_brackets_the_estimate_and_counts_failures():
    rng = np.random.default_rng(0)
    n = 400
    pred = pd.DataFrame({"position_id": np.repeat(np.arange(80), 5)})
    for m in col.METHODS:
        pred[col.error_m(m)] = rng.lognormal(size=n)
    pred.loc[:9, col.error_m("solver")] = np.inf  # 2.5 % failures
    pred[col.radius("fixed", 0.8)] = np.percentile(pred[col.error_m("gate")], 80)
    ci = position_bootstrap_ci(pred, [0.8], ["fixed"], n_boot=300)
    low, high = ci["errors"]["gate"]["p95"]
    assert low < np.percentile(pred[col.error_m("gate")], 95) < high
    assert ci["errors"]["solver"]["p99"][1] == np.inf  # the failures reach p99
    lo, hi = ci["coverage"]["fixed"]["0.8"]
    assert lo < 0.8 < hi


@pytest.mark.slow
def test_cross_fit_end_to_end(compose_cfg, tmp_path):
    cfg = compose_cfg(
        [
            "+site=frozen_lake",
            "+experiment=smoke",
            f"paths.outputs_dir={tmp_path / 'outputs'}",
            "tracking=none",
            "model.n_estimators=20",
            "protocol=cross_fit",
            "protocol.n_folds=3",
            "gate=learned",
            "conformal=all",
            "conformal.ellipse=true",
            "pipeline.selective.enabled=true",
            "pipeline.selective.delta=0.2",
            "+pipeline.extra_gates.box={_target_: plugins.gates.bounding_box.BoundingBoxGate}",
        ]
    )
    metrics = run_experiment(cfg, tmp_path / "run")
    pred = pd.read_parquet(tmp_path / "run" / "predictions.parquet")
    assert len(pred) == 120 and pred["event_id"].is_unique  # every simulated event, once
    assert set(pred["fold"]) == {0, 1, 2}
    assert (pred[col.error_m("oracle")] <= pred[col.error_m("gate")] + 1e-12).all()
    assert len(metrics["gate"]["by_split"]) == 3 and all("threshold" in g for g in metrics["gate"]["by_split"])
    assert metrics["gate"]["diagnostics"]["threshold"] == pytest.approx(np.median([g["threshold"] for g in metrics["gate"]["by_split"]]))
    assert set(metrics["ci95"]["coverage"]) == {
        "fixed",
        "gdop_scaled",
        "gdop_only",
        "error_ratio",
        "mondrian_gdop",
        "gdop_by_region",
        "cqr",
    }
    assert "p95_gate_over_oracle" in metrics["gate_gap"] and "p95_gate_box_over_oracle" in metrics["gate_gap"]
    assert "gate_box" in metrics["errors"] and (pred[col.error_m("oracle")] <= pred[col.error_m("gate_box")] + 1e-12).all()
    assert set(metrics["ellipse"]) == {"0.5", "0.8", "0.95"} and 0 < metrics["ellipse"]["0.95"]["coverage"] <= 1
    assert (pred[col.ellipse(0.95, "a_m")] >= pred[col.ellipse(0.95, "b_m")]).all()
    assert len(metrics["selective_by_split"]) == 3
    placed = pred["placed"].to_numpy(bool)
    assert set(pred.loc[~placed, "abstain_reason"]) <= {
        "no estimate",
        "predicted error above the certified threshold",
        trust.REASON_ABSTAIN,
    }
    assert metrics["selective"]["share_placed"] == pytest.approx(placed.mean())
    assert [r["share_placed"] for r in metrics["risk_coverage"]][0] == 1.0
