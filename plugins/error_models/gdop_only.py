"""GDOP-only error model: predicted error = k × GDOP, with k the median of error / GDOP."""

from __future__ import annotations

from typing import Any

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.utils.validation import check_is_fitted

from acoustlab.core import columns as col
from acoustlab.core.errors import DataError


class GdopOnlyErrorModel(RegressorMixin, BaseEstimator):
    """The geometry-only baseline: scale the GDOP column (``solver__gdop``) by one factor (scikit-learn estimator).

    Parameters
    ----------
    column : str
        Feature column holding the GDOP.
    """

    def __init__(self, column: str = col.SOLVER_GDOP) -> None:
        self.column = column

    def _gdop(self, X: Any) -> np.ndarray:
        if self.column not in getattr(X, "columns", []):
            raise DataError(f"the GDOP-only error model needs feature column {self.column!r}")
        g = X[self.column].to_numpy(dtype=float)
        return np.where(np.isfinite(g), g, np.nanmedian(g) if np.isfinite(g).any() else 1.0)

    def fit(self, X: Any, y: np.ndarray) -> GdopOnlyErrorModel:
        """Fit ``scale_`` = median(error / GDOP) in m."""
        ratio = np.asarray(y, dtype=float) / np.maximum(self._gdop(X), 1e-9)
        self.scale_ = float(max(np.median(ratio[np.isfinite(ratio)]), 1e-6))
        return self

    def predict(self, X: Any) -> np.ndarray:
        """(B,) predicted error scale in m."""
        check_is_fitted(self, "scale_")
        return self.scale_ * np.maximum(self._gdop(X), 1e-9)
