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


def positions_needed(level: float) -> int:
    """How many exchangeable calibration positions a finite-sample guarantee at ``level`` needs: ⌈level / (1 − level)⌉.

    Split conformal over n units reaches ``level`` only when ⌈(n + 1)·level⌉ ≤ n: 19 positions for 0.95, 4 for 0.8, 1 for 0.5.
    """
    return int(math.ceil(level / (1 - level) - 1e-9))


def subsampled_position_quantile(scores: np.ndarray, groups: np.ndarray, level: float, seed: int = 0) -> float:
    """A conformal quantile with a finite-sample guarantee over positions: one event per position, drawn at random.

    With n calibration positions exchangeable with a new one (the spots are not chosen to suit the
    method), one score drawn uniformly from each position's events gives n exchangeable scores, and
    a random event of the new position is one more: its score is at most the ⌈(n+1)·level⌉-th
    smallest with probability ≥ ``level``, for any number of events per position and any
    dependence within a position ("subsampling once", Dunn, Wasserman & Ramdas 2022; Lee, Barber &
    Willett 2023 study such hierarchical guarantees in finite samples). The price is variance: only
    n scores count. Returns ``inf`` with fewer than ``positions_needed(level)`` positions.

    Parameters
    ----------
    scores : numpy.ndarray
        (N,) finite non-conformity scores.
    groups : numpy.ndarray
        (N,) the position of each score.
    level : float
        Nominal coverage in (0, 1).
    seed : int
        Seed of the draw (the same inputs give the same quantile).
    """
    scores, groups = np.asarray(scores, dtype=float), np.asarray(groups)
    if scores.size == 0 or groups.shape != scores.shape:
        raise ValueError("position-level calibration needs scores and one group per score")
    order = np.lexsort((scores, groups))  # by position, then by score: the draw does not depend on the rows' order
    codes, start, counts = np.unique(groups[order], return_index=True, return_counts=True)
    pick = np.random.default_rng(seed).integers(0, counts)
    return conformal_quantile(scores[order][start + pick], level)


def grouped_conformal_quantile(scores: np.ndarray, groups: np.ndarray, level: float) -> float:
    """A conformal quantile whose guarantee is over *groups* (source positions), not events: pooled CDFs (asymptotic).

    Events at one position share its propagation; when a position's events are not exchangeable
    with other positions' (field playbacks at a handful of spots), the event-level quantile
    over-weights positions with many events and its n + 1 correction counts events, not
    positions. This pools the positions' empirical CDFs, each weighing 1/n (n positions), and
    takes the smallest score t with pooled CDF(t) ≥ level × (1 + 1/n): the "pooling CDFs"
    method for two-layer hierarchical data (Dunn, Wasserman & Ramdas 2022). It uses every event,
    but its coverage of a random event of a new position reaches ``level`` only asymptotically
    (many positions); with a few spots use ``subsampled_position_quantile``, whose guarantee holds
    in finite samples. Returns ``inf`` where level × (1 + 1/n) > 1 (too few positions: 19 for 0.95).

    Parameters
    ----------
    scores : numpy.ndarray
        (N,) finite non-conformity scores.
    groups : numpy.ndarray
        (N,) the position of each score.
    level : float
        Nominal coverage in (0, 1).
    """
    scores, groups = np.asarray(scores, dtype=float), np.asarray(groups)
    if not 0 < level < 1:
        raise ValueError(f"coverage level must be in (0, 1); got {level}")
    if scores.size == 0 or not np.isfinite(scores).all() or groups.shape != scores.shape:
        raise ValueError("grouped conformal calibration needs finite scores and one group per score")
    _, inverse, counts = np.unique(groups, return_inverse=True, return_counts=True)
    n = counts.size
    target = level * (1 + 1 / n)
    if target > 1 + 1e-12:
        return math.inf
    order = np.argsort(scores, kind="stable")
    pooled = np.cumsum((1.0 / (n * counts[inverse]))[order])
    k = int(np.searchsorted(pooled, min(target, 1.0) - 1e-12))
    return float(scores[order][min(k, scores.size - 1)])


def selective_threshold(score: np.ndarray, gross: np.ndarray, delta: float, epsilon: float) -> tuple[float, list[dict[str, float]]]:
    """The most permissive threshold on ``score`` whose share of gross errors among placed events is ≤ δ, with confidence 1 − ε.

    Learn then Test (Angelopoulos et al. 2021) with fixed-sequence testing: candidate thresholds
    (the distinct calibration scores) are visited from the strictest (fewest events placed) to the
    most permissive. For each, the null "share(gross | score ≤ t) > δ" is tested with the exact
    binomial tail P(Bin(n_placed, δ) ≤ k_gross); the sequence stops at the first threshold whose
    p-value exceeds ε, and the last rejected one is returned. Because the tests are visited in a
    fixed order, the family-wise error is ε without a multiplicity correction. The sequence starts
    at the first threshold placing enough events for a certificate to be possible
    (n ≥ log ε / log(1 − δ): 230 events for δ = 1 %, ε = 0.1).

    Parameters
    ----------
    score : numpy.ndarray
        (n,) calibration scores (e.g. the error model's predicted error, m): place where score ≤ t.
    gross : numpy.ndarray
        (n,) bool, True where the calibration event's error is gross.
    delta : float
        Tolerated share of gross errors among placed events, in (0, 1).
    epsilon : float
        Tolerated probability that the guarantee fails, in (0, 1).

    Returns
    -------
    threshold : float
        −inf when not even the strictest threshold can be certified (nothing is placed).
    path : list of dict
        ``threshold, n_placed, n_gross, p_value`` of every visited threshold.
    """
    from scipy.stats import binom

    if not 0 < delta < 1 or not 0 < epsilon < 1:
        raise ValueError(f"selective delta and epsilon must lie in (0, 1); got {delta}, {epsilon}")
    score = np.asarray(score, dtype=float)
    gross = np.asarray(gross, dtype=bool)
    order = np.argsort(score, kind="stable")
    sorted_score, sorted_gross = score[order], gross[order]
    n_placed = np.arange(1, score.size + 1)
    n_gross = np.cumsum(sorted_gross)
    last = np.r_[sorted_score[1:] != sorted_score[:-1], True]  # the last event of each distinct score
    # the sequence starts where a certificate is possible at all: n placed events without a gross
    # error give p = (1 − δ)^n, which is ≤ ε only from n ≥ log ε / log(1 − δ) on
    n_min = math.ceil(math.log(epsilon) / math.log1p(-delta))
    threshold, path = -math.inf, []
    for k in np.flatnonzero(last & (n_placed >= n_min)):
        p_value = float(binom.cdf(n_gross[k], n_placed[k], delta))
        path.append({"threshold": float(sorted_score[k]), "n_placed": int(n_placed[k]), "n_gross": int(n_gross[k]), "p_value": p_value})
        if p_value > epsilon:
            break
        threshold = float(sorted_score[k])
    return threshold, path
