"""Field protocols: withheld positions never reach training or calibration; runs end to end."""

import numpy as np
import pandas as pd
import pytest

from acoustlab.dataset import Dataset
from acoustlab.protocols.field import FIELD_POSITION_OFFSET, LopoProtocol, combine


def toy(n_sim_pos=50, per=4, n_field_pos=6, per_field=10):
    sim_ev = pd.DataFrame({"event_id": np.arange(n_sim_pos * per), "position_id": np.repeat(np.arange(n_sim_pos), per),
                           "x_m": 0.0, "y_m": 0.0})
    field_ev = pd.DataFrame({"event_id": np.arange(n_field_pos * per_field), "position_id": np.repeat(np.arange(n_field_pos), per_field),
                             "x_m": 1.0, "y_m": 1.0})
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


@pytest.mark.slow
@pytest.mark.parametrize("protocol", ["field_eval", "lopo"])
def test_field_protocols_end_to_end(compose_cfg, tmp_path, protocol):
    from acoustlab.app import run_experiment

    cfg = compose_cfg(["+site=frozen_lake", "+experiment=smoke", f"protocol={protocol}", "field=playback_standin",
                       "field.stimuli={europe: 3, north_america: 3}", "gate=hybrid", "conformal=all", "tracking=none",
                       f"paths.outputs_dir={tmp_path}"])
    metrics = run_experiment(cfg, tmp_path / "run", {"protocol": protocol})
    preds = pd.read_parquet(tmp_path / "run" / "predictions.parquet")
    assert set(preds["position_id"]) == set(range(6))
    assert metrics["excluded_from_summary"] == (preds["hardware_failure"]).sum() > 0
    assert metrics["errors"]["gate"]["n"] == (~preds["hardware_failure"]).sum()
    assert "tau_star_db" in metrics and set(metrics["coverage"]) == {"fixed", "gdop_scaled", "mondrian_gdop"}
    if protocol == "lopo":
        assert (preds["withheld_position"] == preds["position_id"]).all()
