"""Constant error model: every event gets the same predicted error scale."""

from __future__ import annotations

from typing import Any

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.utils.validation import check_is_fitted

from acoustlab.core.errors import ConfigError


class ConstantErrorModel(RegressorMixin, BaseEstimator):
    """Predicts one statistic of the training errors for every event (scikit-learn estimator).

    With the fixed conformal scorer this reduces to plain split-conformal on the raw error.

    Parameters
    ----------
    statistic : {"median", "mean"}
        Statistic of the training errors (m) to predict.
    """

    def __init__(self, statistic: str = "median") -> None:
        self.statistic = statistic

    def fit(self, X: Any, y: np.ndarray) -> ConstantErrorModel:
        """Store the statistic of the errors ``y`` (m) as ``constant_``."""
        if self.statistic not in ("median", "mean"):
            raise ConfigError(f"error_model.statistic must be 'median' or 'mean'; got {self.statistic!r}")
        y = np.asarray(y, dtype=float)
        if y.size == 0 or not np.isfinite(y).all():
            raise ValueError("ConstantErrorModel.fit needs a non-empty array of finite errors")
        value = float(np.median(y) if self.statistic == "median" else np.mean(y))
        self.constant_ = max(value, 1e-6)
        self.n_features_in_ = getattr(X, "shape", (0, 0))[1]
        return self

    def predict(self, X: Any) -> np.ndarray:
        """(B,) the stored constant, in m."""
        check_is_fitted(self, "constant_")
        return np.full(len(X), self.constant_)
