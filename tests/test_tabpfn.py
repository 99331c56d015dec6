"""TabPFN plugins on a tiny randomly initialised checkpoint of the real architecture (built here).

The checkpoint's predictions are meaningless (random weights): these tests check the real code
path — loading, fitting, batched prediction, quantiles, cloning, the weights preflight — not
accuracy. Tests that need real weights carry the ``needs_weights`` marker.
"""

import numpy as np
import pytest

tabpfn = pytest.importorskip("tabpfn", reason='TabPFN is an optional extra: pip install -e ".[tabpfn]"')
torch = pytest.importorskip("torch")

from acoustlab.core.errors import ConfigError  # noqa: E402
from plugins.models.tabpfn_models import TabPFNErrorModel, TabPFNPointModel  # noqa: E402


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    from plugins.models.tabpfn_checkpoint import build_random_checkpoint

    return str(build_random_checkpoint(tmp_path_factory.mktemp("tabpfn") / "tiny-regressor.ckpt"))


def data(n=120, d=6, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, d)).astype(np.float32)
    return x, (x[:, 0] * 3 + rng.normal(size=n)).astype(np.float32)


def test_fit_predict_in_batches_and_quantiles(tiny_checkpoint):
    x, y = data()
    model = TabPFNPointModel(model_path=tiny_checkpoint, n_estimators=1, device="cpu", batch_size=25).fit(x[:100], y[:100])
    pred = model.predict(x[100:])
    assert pred.shape == (20,) and np.isfinite(pred).all()
    q = model.predict_quantiles(x[100:], [0.1, 0.5, 0.9])
    assert q.shape == (20, 3) and (np.diff(q, axis=1) >= -1e-6).all()


def test_error_model_predicts_a_positive_quantile(tiny_checkpoint):
    x, y = data()
    err = TabPFNErrorModel(model_path=tiny_checkpoint, n_estimators=1, device="cpu").fit(x, np.abs(y))
    assert (err.predict(x[:10]) > 0).all()


def test_a_saved_tabpfn_model_holds_no_torch_object_and_predicts_the_same(tiny_checkpoint, tmp_path):
    """Saved as settings and training rows (no torch object, nothing run on load), refitted on first use: the same
    predictions bit for bit; a checkpoint replaced since the fit is named in one line."""
    import shutil

    from acoustlab.core.errors import DataError
    from acoustlab.method.saved import load_method, save_method

    x, y = data()
    ckpt = tmp_path / "weights.ckpt"
    shutil.copy(tiny_checkpoint, ckpt)
    model = TabPFNErrorModel(model_path=str(ckpt), n_estimators=1, device="cpu").fit(x[:100], np.abs(y[:100]))
    digest = save_method(model, tmp_path / "method", "key")
    loaded = load_method(tmp_path / "method", digest)
    assert getattr(loaded, "regressor_", None) is None  # what was saved holds no TabPFN regressor
    np.testing.assert_array_equal(loaded.predict(x[100:]), model.predict(x[100:]))
    from plugins.models.tabpfn_checkpoint import build_random_checkpoint

    build_random_checkpoint(ckpt, seed=1)  # other weights under the same name
    with pytest.raises(DataError, match="not the one this method was fitted with"):
        load_method(tmp_path / "method", digest).predict(x[100:])


def test_clone_and_row_cap(tiny_checkpoint):
    from sklearn.base import clone

    model = TabPFNPointModel(model_path=tiny_checkpoint, n_estimators=1, device="cpu")
    assert clone(model).get_params() == model.get_params()
    x, y = data(n=1001)
    with pytest.raises(ConfigError, match="1,000"):
        model.fit(x, y)


def test_row_limit_is_checked_against_tabpfns_pretraining_limit():
    assert TabPFNPointModel().max_train_rows == 1000 and TabPFNErrorModel().max_train_rows == 1000
    with pytest.raises(ConfigError, match="model.max_train_rows must be between 2 and 1000 .*ignore_pretraining_limits=true; got 5000"):
        TabPFNPointModel(max_train_rows=5000)
    with pytest.raises(ConfigError, match="error_model.max_train_rows=null"):
        TabPFNErrorModel(max_train_rows=None)
    assert TabPFNPointModel(max_train_rows=5000, ignore_pretraining_limits=True).max_train_rows == 5000


def test_missing_weights_give_one_clear_message(tmp_path):
    with pytest.raises(ConfigError, match="TabPFN weights not found .*download_all_models.*TABPFN_MODEL_CACHE_DIR.*non-commercial"):
        TabPFNPointModel(model_path=str(tmp_path / "absent.ckpt")).preflight()


@pytest.mark.slow
def test_smoke_run_with_tabpfn_point_and_error_models(tiny_checkpoint, compose_cfg, tmp_path):
    from acoustlab.run.app import run_experiment

    cfg = compose_cfg(
        [
            "+site=frozen_lake",
            "+experiment=smoke",
            "model=tabpfn",
            "error_model=tabpfn",
            "tracking=none",
            f"model.model_path={tiny_checkpoint}",
            f"error_model.model_path={tiny_checkpoint}",
            "model.n_estimators=1",
            "error_model.n_estimators=1",
            "model.device=cpu",
            "error_model.device=cpu",
            f"paths.outputs_dir={tmp_path}",
        ]
    )
    metrics = run_experiment(cfg, tmp_path / "run", {"model": "tabpfn"})
    assert metrics["errors"]["model"]["n"] > 0 and np.isfinite(metrics["errors"]["model"]["p50"])


def test_preflight_stops_a_run_before_simulation(compose_cfg, tmp_path):
    from acoustlab.run.app import run_experiment

    cfg = compose_cfg(
        [
            "+site=frozen_lake",
            "+experiment=smoke",
            "model=tabpfn",
            f"model.model_path={tmp_path / 'none.ckpt'}",
            "tracking=none",
            f"paths.outputs_dir={tmp_path}",
        ]
    )
    with pytest.raises(ConfigError, match="TabPFN weights not found"):
        run_experiment(cfg, tmp_path / "run")
    assert not (tmp_path / "cache").exists()


@pytest.mark.needs_weights
def test_real_weights_learn_a_simple_function():
    x, y = data(n=300)
    model = TabPFNPointModel(n_estimators=2).fit(x[:250], y[:250])
    assert np.corrcoef(model.predict(x[250:]), y[250:])[0, 1] > 0.8


class _Payload:
    """An object a pickle would rebuild by running code: what a hostile checkpoint carries."""

    def __reduce__(self):
        return (print, ("code ran while loading",))


def test_a_checkpoint_holding_code_is_refused_before_tabpfn_loads_it(tmp_path, capsys):
    hostile = tmp_path / "hostile.ckpt"
    torch.save({"state_dict": {}, "config": _Payload()}, hostile)
    with pytest.raises(ConfigError, match=r"model.model_path: .*hostile.ckpt cannot be loaded as weights only"):
        TabPFNPointModel(model_path=str(hostile)).preflight()
    assert "code ran" not in capsys.readouterr().out


def test_a_checkpoint_checksum_is_verified(tiny_checkpoint):
    import hashlib
    from pathlib import Path

    digest = hashlib.sha256(Path(tiny_checkpoint).read_bytes()).hexdigest()
    TabPFNPointModel(model_path=tiny_checkpoint, checkpoint_sha256=digest).preflight()  # the real architecture loads as weights only
    with pytest.raises(ConfigError, match="error_model.checkpoint_sha256: .* expected 00"):
        TabPFNErrorModel(model_path=tiny_checkpoint, checkpoint_sha256="00" * 32).preflight()
