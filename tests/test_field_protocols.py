"""Field protocols: withheld positions never reach training or calibration; runs end to end."""

import numpy as np
import pandas as pd
import pytest

from acoustlab.core.errors import ConfigError
from acoustlab.method.pipeline import LocalizationPipeline, MethodResult
from acoustlab.method.protocols.field import (
    FIELD_POSITION_OFFSET,
    FieldEvalProtocol,
    LopoProtocol,
    combine,
)
from acoustlab.stages.dataset import Dataset


def toy(n_sim_pos=50, per=4, n_field_pos=6, per_field=10):
    sim_ev = pd.DataFrame(
        {"event_id": np.arange(n_sim_pos * per), "position_id": np.repeat(np.arange(n_sim_pos), per), "x_m": 0.0, "y_m": 0.0}
    )
    field_ev = pd.DataFrame(
        {
            "event_id": np.arange(n_field_pos * per_field),
            "position_id": np.repeat(np.arange(n_field_pos), per_field),
            "x_m": 1.0,
            "y_m": 1.0,
        }
    )
    feats = lambda n: pd.DataFrame({"tdoa__lag_0_1_s": np.zeros(n)})  # noqa: E731
    return Dataset(sim_ev, feats(len(sim_ev)), "a"), Dataset(field_ev, feats(len(field_ev)), "b")


def test_lopo_never_trains_on_the_withheld_position():
    sim, field = toy()
    features, events, sim_rows, field_rows = combine(sim, field)
    groups = events["position_id"].to_numpy()
    assert not set(groups[sim_rows]) & set(groups[field_rows])  # ids never collide
    seen = []
    for pos, train, test in LopoProtocol(field_fraction=0.2, max_train_rows=100).splits(events, sim_rows, field_rows):
        assert set(groups[test]) == {pos}
        assert pos not in set(groups[train])
        assert train.size <= 100
        assert (groups[train] >= FIELD_POSITION_OFFSET).sum() == 20  # the field share of the budget
        seen.append(pos)
    assert len(seen) == 6


class SpyPipeline:
    """Records the training (and so calibration: it is out-of-fold over training rows) and test positions."""

    def __init__(self):
        self.calls = []

    def fit_predict(self, features, events, train, test):
        groups = events["position_id"].to_numpy()
        self.calls.append((set(groups[train]), set(groups[test])))
        predictions = pd.DataFrame({"event_id": events["event_id"].to_numpy()[test], "position_id": groups[test]})
        return MethodResult(predictions, [{"gate": {"tau_star_db": float(len(self.calls))}}])


@pytest.mark.parametrize("protocol", [FieldEvalProtocol(max_train_rows=100), LopoProtocol(field_fraction=0.3, max_train_rows=100)])
def test_protocols_never_train_or_calibrate_on_a_withheld_position(protocol):
    sim, field = toy()
    spy = SpyPipeline()
    result = protocol.run(sim, spy, field_recordings=field)
    out = result.predictions
    field_ids = {FIELD_POSITION_OFFSET + p for p in range(6)}
    for train_pos, test_pos in spy.calls:
        assert not train_pos & test_pos
        assert test_pos <= field_ids
        if isinstance(protocol, FieldEvalProtocol):
            assert not train_pos & field_ids  # trained on simulation only
    assert set().union(*(t for _, t in spy.calls)) == field_ids  # every field position is evaluated
    assert len(spy.calls) == (1 if isinstance(protocol, FieldEvalProtocol) else 6)
    assert len(out) == len(field.events)
    # one diagnostics entry per split, each from that split's own fitted gate
    assert [d["gate"]["tau_star_db"] for d in result.split_diagnostics] == [float(k + 1) for k in range(len(spy.calls))]


@pytest.mark.slow
@pytest.mark.parametrize("protocol", ["field_eval", "lopo"])
def test_field_protocols_end_to_end(compose_cfg, tmp_path, protocol):
    from acoustlab.run.app import run_experiment

    cfg = compose_cfg(
        [
            "+site=frozen_lake",
            "+experiment=smoke",
            f"protocol={protocol}",
            "field=playback_standin",
            "field.stimuli={europe: 3, north_america: 3}",
            "model.n_estimators=40",
            "gate=hybrid",
            "conformal=all",
            "tracking=none",
            f"paths.outputs_dir={tmp_path}",
        ]
    )
    metrics = run_experiment(cfg, tmp_path / "run", {"protocol": protocol})
    preds = pd.read_parquet(tmp_path / "run" / "predictions.parquet")
    assert set(preds["position_id"]) == set(range(6))
    assert metrics["excluded_from_summary"] == (preds["hardware_failure"]).sum() > 0
    assert metrics["errors"]["gate"]["n"] == (~preds["hardware_failure"]).sum()
    assert metrics["gate"]["name"] == "HybridGate" and "tau_star_db" in metrics["gate"]["diagnostics"]
    assert set(metrics["coverage"]) == {"fixed", "gdop_scaled", "gdop_only", "error_ratio", "mondrian_gdop", "gdop_by_region", "cqr"}
    if protocol == "lopo":
        assert (preds["withheld_position"] == preds["position_id"]).all()
        # τ* is chosen per fold by that fold's own gate and reported per fold (not the last fold's only)
        by_split = metrics["gate"]["by_split"]
        assert [d["split"] for d in by_split] == [f"withheld_position={p}" for p in range(6)]
        assert metrics["gate"]["diagnostics"]["tau_star_db"] == pytest.approx(np.median([d["tau_star_db"] for d in by_split]))
        assert all(5 < len(d["tau_grid"]) <= 20 for d in by_split)  # quantiles of the training energy residuals


@pytest.mark.slow
def test_field_eval_with_calibration_spots_tests_on_the_other_positions(compose_cfg, tmp_path):
    """protocol.calibration_positions=K: K field positions join training and calibrate (position-level); the rest are the test."""
    from acoustlab.run.app import build_run, prepare_data
    from acoustlab.run.registry import build

    cfg = compose_cfg(
        [
            "+site=frozen_lake",
            "+experiment=smoke",
            "protocol=field_eval",
            "field=playback_standin",
            "protocol.calibration_positions=3",
            f"paths.outputs_dir={tmp_path}",
        ]
    )
    built = build_run(cfg)
    data = prepare_data(cfg, built)
    result = built.protocol.run(data.dataset, LocalizationPipeline(built.components), field_recordings=data.field_data)
    field_positions = np.unique(data.field_data.events["position_id"])
    tested = np.unique(result.predictions["position_id"])
    assert tested.size == field_positions.size - 3 and set(tested) < set(field_positions)
    calibration = result.split_diagnostics[0]["calibration"]
    assert calibration["on"] == "field" and calibration["n_positions"] == 3 and "spot" in calibration["guarantee"]
    with pytest.raises(ConfigError, match="leaves no test position"):
        build(compose_cfg(["+site=frozen_lake", "protocol=field_eval", "protocol.calibration_positions=99"]).protocol, "protocol").run(
            data.dataset, LocalizationPipeline(built.components), field_recordings=data.field_data
        )
