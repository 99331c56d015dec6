"""Fixed split-conformal scorer: score = error / predicted error, one quantile per level."""

from __future__ import annotations

import numpy as np

from acoustlab.toolkit.conformal import conformal_quantile


class FixedConformal:
    """Standard split conformal on the error model's output.

    Score s_i = e_i / ê_i (e: 2-D error in m, ê: predicted error in m); the radius at level 1 − α is
    q̂ · ê with q̂ the ⌈(n+1)(1−α)⌉-th smallest calibration score.
    """

    def fit(self, error_m: np.ndarray, predicted_m: np.ndarray, gdop: np.ndarray, levels: list[float]) -> "FixedConformal":
        """Calibrate the quantile ``quantiles_`` for each level in ``levels``."""
        scores = np.asarray(error_m, dtype=float) / np.maximum(np.asarray(predicted_m, dtype=float), 1e-9)
        self.levels_ = [float(v) for v in levels]
        self.quantiles_ = np.array([conformal_quantile(scores, v) for v in self.levels_])
        self.n_calibration_ = int(scores.size)
        return self

    def radius(self, predicted_m: np.ndarray, gdop: np.ndarray) -> np.ndarray:
        """(B, L) radii in m."""
        if not hasattr(self, "quantiles_"):
            raise RuntimeError("FixedConformal.radius called before fit")
        return np.asarray(predicted_m, dtype=float)[:, None] * self.quantiles_[None, :]
