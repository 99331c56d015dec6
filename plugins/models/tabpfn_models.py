"""TabPFN point and error models with the real ``tabpfn`` package (extra: ``pip install -e ".[tabpfn]"``).

One regressor per coordinate (the pipeline clones the point model for x and for y). TabPFN is
an in-context learner: ``fit`` stores the training rows, ``predict`` runs the transformer, in
batches. Weights are never downloaded here: ``TabPFNPointModel.preflight`` checks that the
checkpoint exists before any simulation runs and otherwise stops with one message on how to get it.

A fitted model is stored as its settings and training rows, never as TabPFN's torch objects (a
saved method is read without running code: ``acoustlab.method.saved``): loaded, it fits TabPFN
again on those rows when first used, from the same checkpoint (its SHA-256 recorded at the fit
and checked), which gives the same predictions (TabPFN's fit is deterministic under
``random_state``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.utils.validation import check_is_fitted

from acoustlab.core.digests import file_sha256
from acoustlab.core.errors import ConfigError, DataError

WEIGHTS_HELP = (
    "TabPFN weights not found at {path}. Download them once on a machine with internet: "
    "python -c 'from tabpfn.model_loading import download_all_models; download_all_models()' "
    "(v2.5 and later need a Hugging Face licence acceptance and TABPFN_TOKEN), then point "
    "TABPFN_MODEL_CACHE_DIR at the folder or set model.model_path=/path/to/the/weights (.ckpt or .safetensors). Licences: "
    "v2 weights are Apache-2.0 with attribution (choose them with model.model_version=v2 or TABPFN_MODEL_VERSION=v2); "
    "v2.5, v2.6, v3 and v3.5 (tabpfn's default) are non-commercial."
)
#: Checkpoints already checked in this process: (path, mtime_ns, size, expected sha256) → None.
_CHECKED: dict[tuple[str, int, int, str | None], None] = {}


def check_checkpoint(path: Path, sha256: str | None, setting: str) -> None:
    """Refuse a checkpoint that does not match ``sha256`` or that holds more than tensors and plain data.

    The tabpfn package loads ``.ckpt`` files with ``torch.load(weights_only=None)``, which on torch
    before 2.6 unpickles arbitrary objects (code can run while loading a file from someone else).
    Here every ``.ckpt`` is first loaded with ``weights_only=True`` (torch's restricted unpickler);
    one that needs more is refused before tabpfn opens it. ``.safetensors`` files hold tensors only.

    Raises
    ------
    ConfigError
        Naming the file and the setting, when the digest differs or the safe load fails.
    """
    stat = path.stat()
    key = (str(path), stat.st_mtime_ns, stat.st_size, sha256)
    if key in _CHECKED:
        return
    if sha256 is not None:
        actual = file_sha256(path)
        if actual != sha256.lower():
            raise ConfigError(
                f"{setting}.checkpoint_sha256: {path} has SHA-256 {actual}, expected {sha256}; the file is not the checkpoint you named"
            )
    if path.suffix != ".safetensors":
        import pickle

        import torch

        try:
            torch.load(str(path), map_location="cpu", weights_only=True)
        except (pickle.UnpicklingError, RuntimeError, AttributeError, TypeError, ValueError, EOFError) as exc:
            reason = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
            raise ConfigError(
                f"{setting}.model_path: {path} cannot be loaded as weights only (torch.load(weights_only=True): {reason}); "
                "it may hold code. Use the .safetensors file of the same model, or a checkpoint from Prior Labs"
            ) from None
    _CHECKED[key] = None


def _tabpfn():
    try:
        import tabpfn
    except ImportError:
        raise ConfigError(
            'model=tabpfn needs the optional dependencies: pip install -e ".[tabpfn]" (on a CPU-only machine install the CPU torch first, e.g. pip install torch --index-url https://download.pytorch.org/whl/cpu, or pip pulls a multi-GB CUDA build)'
        ) from None
    return tabpfn


class TabPFNPointModel(RegressorMixin, BaseEstimator):
    """TabPFN regressor for one coordinate (scikit-learn estimator).

    Parameters
    ----------
    model_path : str
        Checkpoint file, or ``auto`` for the default file of ``model_version`` in the TabPFN cache
        (``TABPFN_MODEL_CACHE_DIR``).
    model_version : str, optional
        ``v2``, ``v2.5``, ``v2.6``, ``v3``, ``v3.5`` for ``auto``; None uses ``TABPFN_MODEL_VERSION``
        or v3.5.
    n_estimators : int
        Ensemble members (8 on a GPU; 1–4 keep CPU runs short).
    device : str
        ``auto`` (CUDA when available), ``cpu`` or ``cuda``.
    ignore_pretraining_limits : bool
        Allow more than 1,000 training rows (TabPFN's pretraining limit). Needed only with
        ``max_train_rows`` above 1,000 or null.
    max_train_rows : int or None
        The most rows this model fits on (default 1,000). The pipeline keeps whole source
        positions up to it, so a larger ``protocol.max_train_rows`` feeds other models (XGBoost)
        more rows in the same run while TabPFN stays within its limit; None: every row.
    batch_size : int
        Rows predicted per call (bounds memory).
    random_state : int
        Seed.
    checkpoint_sha256 : str or None
        SHA-256 (hex) the checkpoint file must have; checked before it is loaded (for a user's own
        or a shared checkpoint). Every ``.ckpt`` is also loaded with ``weights_only=True`` first
        (``check_checkpoint``).
    """

    #: the config group its settings live in (named in error messages)
    config_group = "model"

    def __init__(
        self,
        model_path: str = "auto",
        model_version: str | None = None,
        n_estimators: int = 4,
        device: str = "auto",
        ignore_pretraining_limits: bool = False,
        max_train_rows: int | None = 1000,
        batch_size: int = 2000,
        random_state: int = 0,
        checkpoint_sha256: str | None = None,
    ) -> None:
        if max_train_rows is not None and (max_train_rows < 2 or (max_train_rows > 1000 and not ignore_pretraining_limits)):
            raise ConfigError(
                f"{self.config_group}.max_train_rows must be between 2 and 1000 for TabPFN (its pretraining limit) unless "
                f"{self.config_group}.ignore_pretraining_limits=true; got {max_train_rows}"
            )
        if max_train_rows is None and not ignore_pretraining_limits:
            raise ConfigError(
                f"{self.config_group}.max_train_rows=null (every row) needs {self.config_group}.ignore_pretraining_limits=true for TabPFN"
            )
        self.model_path = model_path
        self.model_version = model_version
        self.n_estimators = n_estimators
        self.device = device
        self.ignore_pretraining_limits = ignore_pretraining_limits
        self.max_train_rows = max_train_rows
        self.batch_size = batch_size
        self.random_state = random_state
        self.checkpoint_sha256 = checkpoint_sha256

    def resolved_path(self) -> Path:
        """The checkpoint file this model will load."""
        _tabpfn()
        from tabpfn.model_loading import resolve_model_path

        version = self.model_version or os.environ.get("TABPFN_MODEL_VERSION", "v3.5")
        path = None if self.model_path in (None, "auto") else str(self.model_path)
        return resolve_model_path(path, "regressor", version)[0][0]

    def preflight(self) -> None:
        """Raise one clear ``ConfigError`` if the weights are missing, differ from ``checkpoint_sha256`` or
        hold more than weights (called before any simulation)."""
        path = self.resolved_path()
        if not path.is_file():
            raise ConfigError(WEIGHTS_HELP.format(path=path))
        check_checkpoint(path, self.checkpoint_sha256, self.config_group)

    def _device(self) -> str:
        if self.device != "auto":
            return self.device
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"

    def _regressor(self):
        tabpfn = _tabpfn()
        return tabpfn.TabPFNRegressor(
            model_path=str(self.resolved_path()),
            n_estimators=int(self.n_estimators),
            device=self._device(),
            ignore_pretraining_limits=bool(self.ignore_pretraining_limits),
            random_state=self.random_state,
        )

    def fit(self, X: Any, y: np.ndarray) -> TabPFNPointModel:
        """Store the training rows in a fresh TabPFN regressor."""
        self.preflight()
        X = np.asarray(X, dtype=np.float32)
        if X.shape[0] > 1000 and not self.ignore_pretraining_limits:
            raise ConfigError(
                f"TabPFN got {X.shape[0]} training rows; cap them at 1,000 or set {self.config_group}.ignore_pretraining_limits=true deliberately"
            )
        self.training_rows_ = (X, np.asarray(y, dtype=np.float32))
        self.checkpoint_fitted_sha256_ = file_sha256(self.resolved_path())
        self.regressor_ = self._regressor().fit(*self.training_rows_)
        self.n_features_in_ = X.shape[1]
        return self

    def __getstate__(self) -> dict[str, Any]:
        """Settings and training rows; TabPFN's fitted regressor (torch objects) is left out and fitted again when used."""
        state = super().__getstate__()
        state.pop("regressor_", None)
        return state

    def _fitted_regressor(self):
        """TabPFN's regressor, fitted again on the stored training rows after loading (same checkpoint, checked)."""
        check_is_fitted(self, "training_rows_")
        if getattr(self, "regressor_", None) is None:
            path = self.resolved_path()
            if not path.is_file() or file_sha256(path) != self.checkpoint_fitted_sha256_:
                raise DataError(
                    f"{self.config_group}: the TabPFN checkpoint {path} is missing or not the one this method was fitted with "
                    f"(SHA-256 {self.checkpoint_fitted_sha256_[:12]}…); point {self.config_group}.model_path at it or fit again"
                )
            check_checkpoint(path, self.checkpoint_fitted_sha256_, self.config_group)
            self.regressor_ = self._regressor().fit(*self.training_rows_)
        return self.regressor_

    def _batched(self, X: Any, **kwargs: Any) -> np.ndarray:
        regressor = self._fitted_regressor()
        X = np.asarray(X, dtype=np.float32)
        parts = [regressor.predict(X[i : i + self.batch_size], **kwargs) for i in range(0, X.shape[0], self.batch_size)]
        if kwargs.get("output_type") == "quantiles":
            return np.concatenate([np.column_stack(p) for p in parts], axis=0)
        return np.concatenate(parts, axis=0)

    def predict(self, X: Any) -> np.ndarray:
        """(B,) predictions (the mean of TabPFN's predictive distribution)."""
        return self._batched(X)

    def predict_quantiles(self, X: Any, quantiles: list[float]) -> np.ndarray:
        """(B, Q) quantiles of the predictive distribution."""
        return self._batched(X, output_type="quantiles", quantiles=list(quantiles))


class TabPFNErrorModel(TabPFNPointModel):
    """TabPFN error model: predicts a quantile (default the median) of the hybrid estimate's error, m.

    The other parameters are ``TabPFNPointModel``'s.

    Parameters
    ----------
    quantile : float
        Quantile of TabPFN's predictive distribution returned by ``predict``.
    """

    config_group = "error_model"

    def __init__(
        self,
        model_path: str = "auto",
        model_version: str | None = None,
        n_estimators: int = 4,
        device: str = "auto",
        ignore_pretraining_limits: bool = False,
        max_train_rows: int | None = 1000,
        batch_size: int = 2000,
        random_state: int = 0,
        quantile: float = 0.5,
        checkpoint_sha256: str | None = None,
    ) -> None:
        super().__init__(
            model_path,
            model_version,
            n_estimators,
            device,
            ignore_pretraining_limits,
            max_train_rows,
            batch_size,
            random_state,
            checkpoint_sha256,
        )
        self.quantile = quantile

    def predict(self, X: Any) -> np.ndarray:
        """(B,) the ``quantile`` of the predicted error distribution, floored at 1 mm."""
        return np.maximum(self.predict_quantiles(X, [self.quantile])[:, 0], 1e-3)
