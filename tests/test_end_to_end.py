"""The smoke experiment end to end: metrics.json complete and sane, cache reuse, determinism, MLflow."""

import json
import logging

import numpy as np
import pandas as pd
import pytest

from acoustlab.core.errors import ConfigError
from acoustlab.run.app import run_experiment


def smoke(compose_cfg, tmp_path, *overrides, site="frozen_lake"):
    """The smoke experiment with outputs under ``tmp_path`` and no tracking."""
    small_model = [] if any(o.startswith("model.n_estimators=") for o in overrides) else ["model.n_estimators=40"]
    return compose_cfg(
        [f"+site={site}", "+experiment=smoke", f"paths.outputs_dir={tmp_path / 'outputs'}", "tracking=none", *small_model, *overrides]
    )


def check_metrics(metrics: dict, n_test_max: int) -> None:
    assert set(metrics["errors"]) >= {"solver", "model", "gate"}
    for method, stats in metrics["errors"].items():
        assert set(stats) >= {"n", "mean", "p50", "p90", "p95", "p99"}
        assert 0 < stats["n"] <= n_test_max
        values = [stats[k] for k in ("mean", "p50", "p90", "p95", "p99")]
        assert all(np.isfinite(values)) and all(v >= 0 for v in values), method
        assert stats["p50"] <= stats["p90"] <= stats["p95"] <= stats["p99"]
    for scorer, by_level in metrics["coverage"].items():
        assert set(by_level) == {"0.5", "0.8", "0.95"}
        assert all(0.0 <= v <= 1.0 for v in by_level.values()), scorer
    assert len(metrics["dataset_hash"]) == 64


@pytest.mark.slow
@pytest.mark.parametrize("site", ["frozen_lake", "forest"])
def test_smoke_run_writes_complete_metrics(compose_cfg, tmp_path, site):
    cfg = smoke(compose_cfg, tmp_path, site=site)
    run_dir = tmp_path / "run"
    metrics = run_experiment(cfg, run_dir, {"model": "xgboost"})
    on_disk = json.loads((run_dir / "metrics.json").read_text())
    assert on_disk["errors"] == metrics["errors"]
    check_metrics(on_disk, n_test_max=int(cfg.data.n_events))
    preds = pd.read_parquet(run_dir / "predictions.parquet")
    assert len(preds) == metrics["errors"]["gate"]["n"]
    assert {"radius__fixed__0.95", "error_gate_m", "substituted"} <= set(preds.columns)
    # radii grow with the nominal level
    assert (preds["radius__fixed__0.5"] <= preds["radius__fixed__0.8"]).all()


@pytest.mark.slow
def test_changing_only_the_model_reuses_simulation_and_features(compose_cfg, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="acoustlab")
    first = run_experiment(smoke(compose_cfg, tmp_path), tmp_path / "a")
    assert any("cache miss: features" in r.message for r in caplog.records)
    caplog.clear()
    second = run_experiment(smoke(compose_cfg, tmp_path, "model=random_forest"), tmp_path / "b")
    messages = [r.message for r in caplog.records]
    assert any("cache hit: features" in m for m in messages)
    assert not any("cache miss" in m for m in messages)
    assert first["dataset_hash"] == second["dataset_hash"]
    assert first["errors"]["model"] != second["errors"]["model"]


@pytest.mark.slow
def test_same_config_same_data_bit_for_bit_without_cache(compose_cfg, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="acoustlab")
    a = run_experiment(smoke(compose_cfg, tmp_path, "cache.enabled=false"), tmp_path / "a")
    b = run_experiment(smoke(compose_cfg, tmp_path, "cache.enabled=false", "data.chunk_size=7"), tmp_path / "b")
    assert a["dataset_hash"] == b["dataset_hash"]
    assert a["errors"] == b["errors"]
    assert any("cache bypassed" in r.message for r in caplog.records)
    assert not (tmp_path / "outputs" / "cache" / "features").exists()
    c = run_experiment(smoke(compose_cfg, tmp_path, "cache.enabled=false", "seed=1"), tmp_path / "c")
    assert c["dataset_hash"] != a["dataset_hash"]


@pytest.mark.slow
def test_interrupted_simulation_resumes_from_finished_chunks(compose_cfg, tmp_path, monkeypatch, caplog):
    from plugins.simulators.outdoor import OutdoorSimulator as FreeFieldSimulator

    original = FreeFieldSimulator.simulate
    calls = {"n": 0}

    def flaky(self, site, event_ids, position_ids, seed):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt("simulated interruption")
        return original(self, site, event_ids, position_ids, seed)

    monkeypatch.setattr(FreeFieldSimulator, "simulate", flaky)
    with pytest.raises(KeyboardInterrupt):
        run_experiment(smoke(compose_cfg, tmp_path), tmp_path / "a")
    partial = list((tmp_path / "outputs" / "cache" / "simulation").glob("*.partial/*.npy"))
    assert len(partial) == 2  # two finished chunks survive
    calls["n"] = 10
    resumed = run_experiment(smoke(compose_cfg, tmp_path), tmp_path / "b")
    assert calls["n"] == 10 + 4 - 2  # 120 events / 32 per chunk = 4 chunks, 2 reused
    monkeypatch.setattr(FreeFieldSimulator, "simulate", original)
    fresh = run_experiment(smoke(compose_cfg, tmp_path / "fresh"), tmp_path / "c")
    assert resumed["dataset_hash"] == fresh["dataset_hash"]


def test_no_test_position_in_training(compose_cfg, tmp_path):
    from acoustlab.run.registry import build

    cfg = smoke(compose_cfg, tmp_path)
    protocol = build(cfg.protocol, "protocol")
    events = pd.DataFrame({"position_id": np.repeat(np.arange(300), 5)})
    train, test = protocol.split(events)
    assert len(train) <= 1000
    assert not set(events.position_id.iloc[train]) & set(events.position_id.iloc[test])
    assert 0.07 < len(test) / len(events) < 0.13


def test_missing_site_in_a_composed_config(compose_cfg, tmp_path):
    cfg = compose_cfg(["+experiment=smoke"])
    with pytest.raises(ConfigError, match=r"\+site="):
        run_experiment(cfg, tmp_path / "run")


@pytest.mark.slow
def test_mlflow_store_holds_the_run(compose_cfg, tmp_path):
    import mlflow

    cfg = smoke(compose_cfg, tmp_path, "tracking=mlflow")
    metrics = run_experiment(cfg, tmp_path / "run", {"model": "xgboost", "site": "frozen_lake"})
    uri = f"sqlite:///{tmp_path / 'outputs' / 'mlflow.db'}"
    client = mlflow.MlflowClient(tracking_uri=uri)
    exp = client.get_experiment_by_name("acoustlab")
    (run,) = client.search_runs([exp.experiment_id])
    assert run.data.params["choice.model"] == "xgboost"
    assert run.data.params["data.n_events"] == "120"
    assert run.data.metrics["error.gate.p50"] == pytest.approx(metrics["errors"]["gate"]["p50"])
    assert run.data.tags["dataset_hash"] == metrics["dataset_hash"]
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert {"metrics.json", "predictions.parquet", "tables"} <= artifacts
    tables = {a.path for a in client.list_artifacts(run.info.run_id, "tables")}
    assert {"tables/errors.json", "tables/coverage.json"} <= tables


@pytest.mark.slow
def test_parallel_and_sharded_generation_give_the_same_data(compose_cfg, tmp_path):
    serial = run_experiment(smoke(compose_cfg, tmp_path / "serial"), tmp_path / "a")
    parallel = run_experiment(smoke(compose_cfg, tmp_path / "parallel", "data.n_jobs=2"), tmp_path / "b")
    assert parallel["dataset_hash"] == serial["dataset_hash"]
    for index in (0, 1):
        out = run_experiment(
            smoke(compose_cfg, tmp_path / "sharded", "data.shard_count=2", f"data.shard_index={index}"), tmp_path / f"s{index}"
        )
        assert out == {"shard": {"index": index, "count": 2}}
    partial = list((tmp_path / "sharded" / "outputs" / "cache" / "simulation").glob("*.partial/*.npy"))
    assert len(partial) == 4  # 120 events in chunks of 32, split over two shards
    final = run_experiment(smoke(compose_cfg, tmp_path / "sharded"), tmp_path / "c")
    assert final["dataset_hash"] == serial["dataset_hash"]


@pytest.mark.slow
def test_leave_one_position_out_calibration(compose_cfg, tmp_path):
    metrics = run_experiment(smoke(compose_cfg, tmp_path, "conformal.calibration_folds=-1", "model.n_estimators=10"), tmp_path / "a")
    assert all(0 <= v <= 1 for v in metrics["coverage"]["fixed"].values())
