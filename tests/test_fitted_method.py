"""A method fitted once predicts new events in any chunks: the rows equal one prediction of all of them, and survive saving."""

import numpy as np
import pandas as pd
import pytest

from acoustlab.core import columns as col
from acoustlab.core.errors import DataError
from acoustlab.method.pipeline import LocalizationPipeline
from acoustlab.method.saved import load_method, save_method
from acoustlab.run.app import build_run, prepare_data


@pytest.mark.slow
def test_predicting_in_chunks_equals_predicting_at_once_with_every_optional_output(compose_cfg, tmp_path, monkeypatch):
    """CQR, ellipses, selective localization and an extra gate: every output is a function of the fitted method and the row."""
    cfg = compose_cfg(
        [
            "+site=frozen_lake",
            "+experiment=smoke",
            f"paths.outputs_dir={tmp_path}",
            "tracking=none",
            "model.n_estimators=20",
            "conformal=all",
            "conformal.ellipse=true",
            "pipeline.selective.enabled=true",
            "pipeline.selective.delta=0.2",
            "+gate@pipeline.extra_gates.box=bounding_box",
        ]
    )
    built = build_run(cfg)
    data = prepare_data(cfg, built).dataset
    groups = data.events[col.POSITION_ID].to_numpy()
    test = np.flatnonzero(groups % 5 == 0)
    train = np.flatnonzero(groups % 5 != 0)
    pipeline = LocalizationPipeline(built.components)
    together = pipeline.fit_predict(data.features, data.events, train, test).predictions
    fitted = pipeline.fit(data.features, data.events, train)
    save_method(fitted, tmp_path / "method", key="test")
    loaded = load_method(tmp_path / "method")
    assert set(loaded.quantile_models) == {"cqr"} and loaded.quantile_training is None  # CQR's quantile model fitted once, kept

    def refit(*args, **kwargs):
        raise AssertionError("CQR's quantile model refitted while predicting")

    monkeypatch.setattr(type(loaded.scorers["cqr"]), "fit_quantiles", refit)
    parts = [loaded.predict(data.features.iloc[rows], data.events.iloc[rows])[0] for rows in np.array_split(test[::-1], 3)]
    chunked = pd.concat(parts, ignore_index=True).iloc[::-1].reset_index(drop=True)
    assert {col.PLACED, "ellipse__0.95__a_m", col.radius("cqr", 0.95), col.error_m("gate_box")} <= set(together.columns)
    pd.testing.assert_frame_equal(chunked, together)


@pytest.mark.slow
def test_a_position_on_both_sides_is_refused(compose_cfg, tmp_path):
    cfg = compose_cfg(["+site=frozen_lake", "+experiment=smoke", f"paths.outputs_dir={tmp_path}", "tracking=none"])
    built = build_run(cfg)
    data = prepare_data(cfg, built).dataset
    rows = np.arange(len(data.events))
    with pytest.raises(DataError, match="a source position appears in both training and test rows"):
        LocalizationPipeline(built.components).fit_predict(data.features, data.events, rows, rows[:5])


def test_a_method_is_loaded_only_with_this_user_s_signature(tmp_path, monkeypatch):
    """Unpickling runs code: a method file and digest replaced together (a received or tampered folder) are refused before
    anything is unpickled; the same folder loads with the key that wrote it."""
    import hashlib
    import json
    import pickle

    from acoustlab.core.errors import DataError
    from acoustlab.method.saved import DIGEST_FILE, METHOD_FILE, load_method, method_key_path, save_method

    monkeypatch.setenv("ACOUSTLAB_KEY_FILE", str(tmp_path / "mine.key"))
    digest = save_method({"a fitted": "method"}, tmp_path / "run", "config-key")
    assert load_method(tmp_path / "run", digest) == {"a fitted": "method"}
    assert method_key_path().stat().st_mode & 0o777 == 0o600

    class Payload:  # what an attacker would ship: code that runs when unpickled
        def __reduce__(self):
            return (open, (str(tmp_path / "pwned"), "w"))

    evil = pickle.dumps(Payload())
    (tmp_path / "run" / METHOD_FILE).write_bytes(evil)
    record = json.loads((tmp_path / "run" / DIGEST_FILE).read_text())
    record["sha256"] = hashlib.sha256(evil).hexdigest()  # the digest beside it updated too
    (tmp_path / "run" / DIGEST_FILE).write_text(json.dumps(record))
    with pytest.raises(DataError, match="was not written with this user's key"):
        load_method(tmp_path / "run", record["sha256"])
    assert not (tmp_path / "pwned").exists()
    save_method({"a fitted": "method"}, tmp_path / "theirs", "config-key")
    monkeypatch.setenv("ACOUSTLAB_KEY_FILE", str(tmp_path / "someone_else.key"))  # a folder made by another user
    with pytest.raises(DataError, match="fit again"):
        load_method(tmp_path / "theirs")
