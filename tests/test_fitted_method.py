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


class _Payload:
    """What an attacker would ship: an object that creates a file when it is rebuilt (unpickled or loaded)."""

    target = ""

    def __reduce__(self):
        return (open, (self.target, "w"))

    def __setstate__(self, state):
        open(state["target"], "w").close()


def _forge(folder, blob: bytes) -> str:
    """Replace a saved method's file with ``blob`` and its recorded digest with the blob's, as a forger would."""
    import hashlib
    import json

    from acoustlab.method.saved import DIGEST_FILE, METHOD_FILE

    (folder / METHOD_FILE).write_bytes(blob)
    record = json.loads((folder / DIGEST_FILE).read_text())
    record["sha256"] = hashlib.sha256(blob).hexdigest()
    (folder / DIGEST_FILE).write_text(json.dumps(record))
    return record["sha256"]


def test_a_forged_method_file_is_refused_before_anything_in_it_runs(tmp_path):
    """No code runs when a method is loaded, whoever wrote the folder: a pickle, a foreign class and a function named in
    the file are refused in one line with its digest updated too; a method saved elsewhere loads with no key."""
    import pickle

    import skops.io as sio

    from acoustlab.core.files import atomic_write_bytes
    from acoustlab.method.saved import load_method, save_method

    digest = save_method({"a fitted": np.arange(3)}, tmp_path / "run", "config-key")
    np.testing.assert_array_equal(load_method(tmp_path / "run", digest)["a fitted"], np.arange(3))
    pwned = tmp_path / "pwned"
    payload = _Payload()
    payload.target = str(pwned)
    forged = {
        "pickle": (pickle.dumps(payload), "not a saved acoustlab method"),
        "class": (sio.dumps({"a fitted": payload}), "names types a saved method never holds.*_Payload"),
        "function": (sio.dumps({"a fitted": atomic_write_bytes}), "never holds.*acoustlab.core.files.atomic_write_bytes"),
    }
    for name, (blob, message) in forged.items():
        sha = _forge(tmp_path / "run", blob)
        with pytest.raises(DataError, match=message):
            load_method(tmp_path / "run", sha)
        assert not pwned.exists(), name
    sha = _forge(tmp_path / "run", b"")  # edited in place: the season's manifest still names the written digest
    with pytest.raises(DataError, match="differs from the expected"):
        load_method(tmp_path / "run", digest)
    # the premise: trusting what the file names would have run the payload
    sio.loads(forged["class"][0], trusted=sio.get_untrusted_types(data=forged["class"][0]))
    assert pwned.exists()


@pytest.mark.parametrize("kind", ["random_forest", "knn", "hist_gradient_boosting", "xgboost"])
def test_every_shipped_estimator_is_saved_and_loaded_without_pickle(kind, tmp_path):
    """The point models, error models and gate classifiers acoustlab ships: each one's fitted state is stored by skops
    with types acoustlab trusts, and loaded it predicts the same."""
    from sklearn.ensemble import HistGradientBoostingClassifier, RandomForestRegressor
    from sklearn.neighbors import KNeighborsRegressor
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler
    from xgboost import XGBRegressor

    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(200, 5)), rng.normal(size=200)
    estimator = {
        "random_forest": lambda: RandomForestRegressor(n_estimators=5, random_state=0).fit(x, y),
        "knn": lambda: make_pipeline(StandardScaler(), KNeighborsRegressor()).fit(x, y),
        "hist_gradient_boosting": lambda: HistGradientBoostingClassifier(max_iter=10).fit(x, y > 0),
        "xgboost": lambda: XGBRegressor(n_estimators=5, n_jobs=1).fit(x, y),
    }[kind]()
    loaded = load_method(tmp_path, save_method({"model": estimator}, tmp_path, kind))["model"]
    np.testing.assert_array_equal(loaded.predict(x), estimator.predict(x))
