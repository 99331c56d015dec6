"""Split-conformal maths shared by the conformal scorer plugins."""

from __future__ import annotations

import math

import numpy as np


def conformal_quantile(scores: np.ndarray, level: float) -> float:
    """The finite-sample conformal quantile: the ⌈(n+1)·level⌉-th smallest score.

    For exchangeable scores a new score falls at or below it with probability ≥ ``level``.
    Returns ``inf`` when ⌈(n+1)·level⌉ > n (too few calibration points for that level).

    Parameters
    ----------
    scores : numpy.ndarray
        (n,) finite non-conformity scores.
    level : float
        Nominal coverage 1 − α in (0, 1).
    """
    scores = np.asarray(scores, dtype=float)
    if not 0 < level < 1:
        raise ValueError(f"coverage level must be in (0, 1); got {level}")
    if scores.size == 0 or not np.isfinite(scores).all():
        raise ValueError("conformal calibration needs a non-empty array of finite scores")
    n = scores.size
    rank = math.ceil((n + 1) * level)
    if rank > n:
        return math.inf
    return float(np.sort(scores)[rank - 1])
