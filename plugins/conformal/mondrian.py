"""Mondrian split conformal by GDOP bins: a separate quantile of e / ê in each GDOP bin."""

from __future__ import annotations

import numpy as np

from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.conformal import conformal_quantile


class MondrianGdopConformal:
    """Score e / ê (as the fixed scorer), calibrated separately within GDOP quantile bins.

    Coverage then holds within each bin (conditionally on the geometry class), not only on average.

    Parameters
    ----------
    n_bins : int
        Number of GDOP bins (edges at calibration quantiles).
    """

    def __init__(self, n_bins: int = 3) -> None:
        if n_bins < 1:
            raise ConfigError(f"conformal n_bins must be >= 1; got {n_bins}")
        self.n_bins = int(n_bins)

    def fit(self, error_m: np.ndarray, predicted_m: np.ndarray, gdop: np.ndarray, levels: list[float]) -> "MondrianGdopConformal":
        """Calibrate ``edges_`` and ``quantiles_`` (bins × levels)."""
        scores = np.asarray(error_m, dtype=float) / np.maximum(np.asarray(predicted_m, dtype=float), 1e-9)
        g = np.asarray(gdop, dtype=float)
        self.edges_ = np.quantile(g, np.linspace(0, 1, self.n_bins + 1)[1:-1]) if self.n_bins > 1 else np.array([])
        bins = np.searchsorted(self.edges_, g, side="right")
        self.levels_ = [float(v) for v in levels]
        self.quantiles_ = np.array([[conformal_quantile(scores[bins == b], v) if (bins == b).any() else np.inf for v in self.levels_] for b in range(self.n_bins)])
        return self

    def radius(self, predicted_m: np.ndarray, gdop: np.ndarray) -> np.ndarray:
        """(B, L) radii in m."""
        if not hasattr(self, "quantiles_"):
            raise RuntimeError("MondrianGdopConformal.radius called before fit")
        bins = np.searchsorted(self.edges_, np.asarray(gdop, dtype=float), side="right")
        return np.asarray(predicted_m, dtype=float)[:, None] * self.quantiles_[bins]
