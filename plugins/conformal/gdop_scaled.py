"""GDOP-scaled split conformal: errors normalised by the GDOP at the estimate."""

from __future__ import annotations

import numpy as np

from acoustlab.toolkit.conformal import conformal_quantile


class GdopScaledConformal:
    """Score s_i = e_i / GDOP_i (GDOP at the hybrid estimate); radius q̂ · GDOP.

    Geometry sets how a timing error maps into position error, so scaling by GDOP makes scores
    closer to exchangeable across the array (narrow radii inside, wide ones where hyperbolas
    meet at grazing angles).
    """

    def fit(self, error_m: np.ndarray, predicted_m: np.ndarray, gdop: np.ndarray, levels: list[float]) -> "GdopScaledConformal":
        """Calibrate ``quantiles_`` (m per unit GDOP) per level."""
        scores = np.asarray(error_m, dtype=float) / np.maximum(np.asarray(gdop, dtype=float), 1e-9)
        self.levels_ = [float(v) for v in levels]
        self.quantiles_ = np.array([conformal_quantile(scores, v) for v in self.levels_])
        return self

    def radius(self, predicted_m: np.ndarray, gdop: np.ndarray) -> np.ndarray:
        """(B, L) radii in m."""
        if not hasattr(self, "quantiles_"):
            raise RuntimeError("GdopScaledConformal.radius called before fit")
        return np.asarray(gdop, dtype=float)[:, None] * self.quantiles_[None, :]
