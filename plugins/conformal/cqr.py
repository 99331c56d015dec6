"""Conformalized quantile regression (CQR, Romano, Patterson & Candès 2019) on the localization error.

Split conformal with one error model adjusts a single prediction ê by a constant per level
(``fixed``). CQR instead fits a quantile regressor q̂_α(x) of the error for every nominal level α
(so the radius already widens where the error model expects wide spread, without GDOP), and
conformalizes each: with calibration scores s_i = e_i − q̂_α(x_i) and Q_α their
⌈(n+1)α⌉-th smallest value, the radius is max(0, q̂_α(x) + Q_α). This is the one-sided form
(an upper bound on a non-negative error), the same guarantee as the other scorers: marginal
coverage ≥ α over exchangeable source positions. Quantile crossings are removed by taking the
running maximum over increasing levels (rearrangement, Chernozhukov et al. 2010), which keeps
coverage and makes radii grow with the level.

The pipeline (``acoustlab.method.pipeline``) sees ``needs_quantiles`` and calls
``ConformalizedQuantile.fit_predict_quantiles`` out-of-fold over training positions for the
calibration quantiles and on all training rows for the test quantiles, on the error model's
features. Without quantiles (``quantiles=None``) the scorer falls back to ê for every level,
which is ``fixed``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd
from sklearn.base import clone

from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.conformal import calibration_quantile, check_calibration_unit


class ConformalizedQuantile:
    """CQR on the error: a quantile model per nominal level, each shifted by its conformal correction.

    Parameters
    ----------
    model : scikit-learn regressor
        The quantile regressor. An estimator with a ``quantile_alpha`` parameter (XGBoost's
        ``reg:quantileerror``) is fitted once for all levels; one with ``quantile`` (scikit-learn's
        ``HistGradientBoostingRegressor(loss="quantile")``) or ``alpha`` (``GradientBoostingRegressor``)
        once per level.
    calibration_unit : {"event", "position"}
        ``event``: the usual quantile over calibration events. ``position``: the positions' score
        CDFs pooled, each position weighing the same (``grouped_conformal_quantile``), a guarantee
        for a new position; a calibration on field spots is always position-level.
    """

    #: the pipeline fits this scorer's quantile model on the error model's features
    needs_quantiles = True

    def __init__(self, model: Any, calibration_unit: str = "event") -> None:
        check_calibration_unit(calibration_unit)
        self.calibration_unit = calibration_unit
        if not hasattr(model, "fit") or not hasattr(model, "get_params"):
            raise ConfigError(f"conformal cqr: model must be a scikit-learn regressor; got {type(model).__name__}")
        self.model = model
        if self._quantile_key() is None:
            raise ConfigError(
                f"conformal cqr: {type(model).__name__} is not a quantile regressor (XGBoost with objective "
                "reg:quantileerror, or an estimator with a quantile or alpha parameter)"
            )

    def _quantile_key(self) -> str | None:
        params = self.model.get_params()
        if "quantile_alpha" in params or params.get("objective") == "reg:quantileerror":
            return "quantile_alpha"
        return next((k for k in ("quantile", "alpha") if k in params), None)

    def fit_quantiles(self, x_fit: pd.DataFrame, error_m: np.ndarray, levels: list[float]) -> Any:
        """The quantile model(s) fitted on (x_fit, error): one XGBoost model for every level, else one per level."""
        key = self._quantile_key()
        if key == "quantile_alpha":
            return clone(self.model).set_params(quantile_alpha=np.asarray(levels, dtype=float)).fit(x_fit, error_m)
        return [clone(self.model).set_params(**{key: float(level)}).fit(x_fit, error_m) for level in levels]

    @staticmethod
    def predict_quantiles(fitted: Any, x_predict: pd.DataFrame, levels: list[float]) -> np.ndarray:
        """(n_predict, L) error quantiles, m, from ``fit_quantiles``' model(s)."""
        if isinstance(fitted, list):
            return np.column_stack([model.predict(x_predict) for model in fitted]).astype(float)
        return np.asarray(fitted.predict(x_predict), dtype=float).reshape(len(x_predict), len(levels))

    def fit_predict_quantiles(self, x_fit: pd.DataFrame, error_m: np.ndarray, x_predict: pd.DataFrame, levels: list[float]) -> np.ndarray:
        """Fit the quantile model(s) on (x_fit, error) and return (n_predict, L) predicted error quantiles, m."""
        return self.predict_quantiles(self.fit_quantiles(x_fit, error_m, levels), x_predict, levels)

    def _quantiles(self, predicted_m: np.ndarray, quantiles: np.ndarray | None) -> np.ndarray:
        if quantiles is None:  # no quantile predictions: the error model's prediction for every level (= fixed)
            return np.repeat(np.asarray(predicted_m, dtype=float)[:, None], len(self.levels_), axis=1)
        quantiles = np.asarray(quantiles, dtype=float)
        if quantiles.shape != (len(predicted_m), len(self.levels_)):
            raise ValueError(f"cqr: quantiles of shape {quantiles.shape}; expected {(len(predicted_m), len(self.levels_))}")
        return quantiles

    def fit(
        self,
        error_m: np.ndarray,
        predicted_m: np.ndarray,
        gdop: np.ndarray,
        levels: list[float],
        quantiles: np.ndarray | None = None,
        groups: np.ndarray | None = None,
    ) -> ConformalizedQuantile:
        """Calibrate one correction per level from calibration errors and their out-of-fold quantile predictions (``groups``: their
        positions, for ``calibration_unit="position"``)."""
        self.levels_ = [float(v) for v in levels]
        scores = np.asarray(error_m, dtype=float)[:, None] - self._quantiles(predicted_m, quantiles)
        self.corrections_ = np.array(
            [calibration_quantile(scores[:, k], level, self.calibration_unit, groups) for k, level in enumerate(self.levels_)]
        )
        self.n_calibration_ = int(scores.shape[0])
        return self

    def radius(self, predicted_m: np.ndarray, gdop: np.ndarray, quantiles: np.ndarray | None = None) -> np.ndarray:
        """(B, L) radii in m (≥ 0, non-decreasing in the level)."""
        if not hasattr(self, "corrections_"):
            raise RuntimeError("ConformalizedQuantile.radius called before fit")
        radii = np.maximum(self._quantiles(predicted_m, quantiles) + self.corrections_[None, :], 0.0)
        order = np.argsort(self.levels_)
        radii[:, order] = np.maximum.accumulate(radii[:, order], axis=1)  # no crossing: wider at a higher level
        return radii
