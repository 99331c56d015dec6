"""The point models at the method's shape: fit and predict on 1,000 training rows of 80 features, 110 test rows.

TabPFN runs a randomly initialised checkpoint of the published v2 regressor's size
(``plugins.models.tabpfn_checkpoint.FULL_SIZE``; real weights cannot be downloaded everywhere): the
timings are those of the real architecture, the predictions mean nothing. A CUDA case runs only where
torch sees a GPU; a case whose package is missing is skipped.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

ROWS, FEATURES, TEST = 1000, 80, 110


def _data() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(ROWS + TEST, FEATURES)).astype(np.float32)
    y = (3 * x[:, 0] + rng.normal(size=len(x))).astype(np.float32)
    return x[:ROWS], y[:ROWS], x[ROWS:]


class PointModels:
    """``fit`` then ``predict`` of one point model (one coordinate)."""

    params = [["xgboost", "tabpfn"], ["cpu", "cuda"]]
    param_names = ["model", "device"]
    quick_params = [["xgboost"], ["cpu"]]

    def setup(self, model: str, device: str) -> None:
        self.x, self.y, self.test = _data()
        if model == "xgboost":
            if device != "cpu":
                raise NotImplementedError("the XGBoost baseline is timed on the CPU")
            from xgboost import XGBRegressor

            self.model = XGBRegressor(n_estimators=300, max_depth=6, learning_rate=0.05, n_jobs=1)
            return
        try:
            import torch

            from plugins.models.tabpfn_checkpoint import FULL_SIZE, build_random_checkpoint
            from plugins.models.tabpfn_models import TabPFNPointModel
        except ImportError as exc:
            raise NotImplementedError(f"TabPFN is not installed ({exc}): pip install -e '.[tabpfn]'") from exc
        if device == "cuda" and not torch.cuda.is_available():
            raise NotImplementedError("no CUDA GPU")
        self._tmp = tempfile.TemporaryDirectory()
        ckpt = build_random_checkpoint(Path(self._tmp.name) / "random-full-size-regressor.ckpt", FULL_SIZE)
        self.model = TabPFNPointModel(model_path=str(ckpt), n_estimators=4, device=device)
        self.device = device

    def time_fit_predict(self, model: str, device: str) -> None:
        self.model.fit(self.x, self.y).predict(self.test)
        if device == "cuda":
            import torch

            torch.cuda.synchronize()
