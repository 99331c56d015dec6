"""Split-conformal maths shared by the conformal scorer plugins."""

from __future__ import annotations

import math

import numpy as np

from acoustlab.core.errors import ConfigError

#: What a calibration's guarantee is over: random events, or random source positions (field spots).
CALIBRATION_UNITS = ("event", "position")
#: How a position-level quantile uses a position's events: all of them pooled, or one drawn at random
#: (at the marginal rank, or at the PAC rank that holds ℓ − ε with probability 1 − δ over calibration sets).
POSITION_METHODS = ("pooled", "subsample", "pac")


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


#: The probability over calibration sets that ``one_set_coverage`` states.
ONE_SET_PROBABILITY = 0.9


def pac_rank(n_positions: int, level: float, delta: float, epsilon: float) -> int | None:
    """The smallest rank k whose score covers at least ``level − epsilon`` with probability ≥ 1 − ``delta`` over calibration sets.

    With one exchangeable score per position, the k-th smallest's coverage of a new position is
    Beta(k, n + 1 − k) given the set (Vovk 2012): k is the smallest with
    P(Beta(k, n + 1 − k) < level − epsilon) ≤ delta, a "probably approximately correct" radius
    (training-conditional, as in Vovk 2012 and Park et al. 2020's PAC prediction sets) where the
    usual rank ⌈(n + 1)·level⌉ holds ``level`` only on average over sets. None where no k ≤ n does
    (``pac_positions_needed``).
    """
    from scipy.stats import beta

    if n_positions < 1:
        return None
    ranks = np.arange(1, n_positions + 1)
    ok = np.flatnonzero(beta.cdf(level - epsilon, ranks, n_positions + 1 - ranks) <= delta)  # falls as k grows
    return int(ranks[ok[0]]) if ok.size else None


def pac_positions_needed(level: float, delta: float, epsilon: float) -> int:
    """How many positions a PAC radius at ``level`` needs: the largest score covers ℓ − ε with probability 1 − δ once
    (ℓ − ε)ⁿ ≤ δ, n = ⌈ln δ / ln(ℓ − ε)⌉ (at δ = 0.1, ε = 0.05: 9 positions for 0.8, 22 for 0.95)."""
    return int(math.ceil(math.log(delta) / math.log(level - epsilon) - 1e-9))


def check_pac(delta: float, epsilon: float) -> None:
    """Refuse a PAC setting outside 0 < δ < 1, 0 ≤ ε < 0.5 (one line naming the value)."""
    if not 0 < delta < 1:
        raise ConfigError(f"conformal pac_delta must lie in (0, 1); got {delta}")
    if not 0 <= epsilon < 0.5:
        raise ConfigError(f"conformal pac_epsilon must lie in [0, 0.5); got {epsilon}")


def one_set_coverage(
    n_positions: int,
    level: float,
    probability: float = ONE_SET_PROBABILITY,
    method: str = "pooled",
    delta: float = 0.1,
    epsilon: float = 0.05,
) -> float | None:
    """The coverage that one calibration set of ``n_positions`` positions gives its radius at ``level`` with ``probability``.

    With one exchangeable score per position the rank k = ⌈(n + 1)·level⌉ gives a radius whose
    coverage of a new position, given the set, is Beta(k, n + 1 − k)-distributed (Vovk 2012's
    training-conditional view of split conformal); its (1 − ``probability``) quantile c is what
    "with probability 0.9 over your spots, this radius covers at least c" states. Exact for
    ``position_method: subsample``; pooling every event of a position scatters less, so there c is
    a lower bound (``tests/test_conformal.py``). With ``method="pac"`` the rank is ``pac_rank``'s. None
    where ``level`` needs more positions than given.
    """
    from scipy.stats import beta

    k = pac_rank(n_positions, level, delta, epsilon) if method == "pac" else math.ceil((n_positions + 1) * level)
    if k is None or k > n_positions:
        return None
    return float(beta.ppf(1 - probability, k, n_positions + 1 - k))


def subsampled_position_quantile(
    scores: np.ndarray, groups: np.ndarray, level: float, seed: int = 0, pac: tuple[float, float] | None = None
) -> float:
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
    pac : (delta, epsilon), optional
        Take the score at ``pac_rank`` instead: it covers at least ``level − epsilon`` of a new
        position's events with probability ≥ 1 − ``delta`` over calibration sets.
    """
    scores, groups = np.asarray(scores, dtype=float), np.asarray(groups)
    if scores.size == 0 or groups.shape != scores.shape:
        raise ValueError("position-level calibration needs scores and one group per score")
    order = np.lexsort((scores, groups))  # by position, then by score: the draw does not depend on the rows' order
    codes, start, counts = np.unique(groups[order], return_index=True, return_counts=True)
    pick = np.random.default_rng(seed).integers(0, counts)
    drawn = scores[order][start + pick]
    if pac is None:
        return conformal_quantile(drawn, level)
    k = pac_rank(drawn.size, level, *pac)
    return math.inf if k is None else float(np.sort(drawn)[k - 1])


def grouped_conformal_quantile(scores: np.ndarray, groups: np.ndarray, level: float) -> float:
    """A conformal quantile whose guarantee is over *groups* (source positions), not events: pooled CDFs, finite-sample.

    Events at one position share its propagation; when a position's events are not exchangeable
    with other positions' (field playbacks at a handful of spots), the event-level quantile
    over-weights positions with many events and its n + 1 correction counts events, not
    positions. This pools the positions' empirical CDFs, each weighing 1/n (n positions), and
    takes the smallest score t with pooled CDF(t) ≥ level × (1 + 1/n): the "pooling CDFs"
    method for two-layer hierarchical data (Dunn, Wasserman & Ramdas 2022) with the new
    position's share, 1/(n + 1), put at +∞. That share makes the guarantee finite-sample under
    hierarchical exchangeability (positions exchangeable, and the events of one position
    exchangeable among themselves; Lee, Barber & Willett 2023): the quantile t* of all n + 1
    positions' pooled CDF is symmetric in the positions, so a random event of the new one falls
    at or below it with probability E[F̂_new(t*)] = E[mean of all F̂_k(t*)] ≥ ``level``, and
    putting the new position's mass at +∞ only raises the quantile. Unlike
    ``subsampled_position_quantile`` it uses every event, so one calibration set's coverage
    scatters less around its mean (``tests/test_conformal.py`` measures both). Returns ``inf``
    where level × (1 + 1/n) > 1 (too few positions: 19 for 0.95).

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


def betting_p_value(losses: np.ndarray, delta: float, alpha: float, seed: int = 0) -> float:
    """p-value of "E[loss] ≥ δ" from independent losses in [0, 1], by betting (Waudby-Smith & Ramdas 2023).

    The capital K_i = Π (1 + λ_k (δ − loss_k)) is a non-negative supermartingale under the null, so
    1 / max K is a valid p-value (Ville's inequality) for any predictable bets λ_k (chosen from the
    losses before k only, with the predictable plug-in rule tuned to ``alpha``; capped so capital
    stays positive). It adapts to the losses' variance, which Hoeffding-type bounds take as the
    worst case. The losses are visited in a random order (``seed``), fixed before looking at them.
    """
    z = np.asarray(losses, dtype=float)[np.random.default_rng(seed).permutation(len(losses))]
    if z.size == 0:
        return 1.0
    i = np.arange(1, z.size + 1)
    mean = (0.5 + np.cumsum(z)) / (i + 1)  # running estimates with a prior of one pseudo-observation (0.5, variance 0.25)
    var = (0.25 + np.cumsum((z - mean) ** 2)) / (i + 1)
    var_before = np.r_[0.25, var[:-1]]  # bet k sees losses 1 … k − 1 only
    bet = np.minimum(np.sqrt(2 * math.log(1 / alpha) / (np.maximum(var_before, 1e-6) * i * np.log(i + 1))), 0.5 / (1 - delta))
    best = max(1.0, float(np.exp(np.cumsum(np.log1p(bet * (delta - z)))).max()))
    return float(min(1.0, 1.0 / best))


def selective_threshold_by_position(
    score: np.ndarray, gross: np.ndarray, groups: np.ndarray, delta: float, epsilon: float, n_candidates: int = 20
) -> tuple[float, list[dict[str, float]]]:
    """``selective_threshold`` with source positions, not detections, as the independent units (clustered errors).

    Detections at one position share its geometry and propagation, so their gross errors come
    together; counting them as independent overstates the evidence. Here each position j gives
    one loss in [0, 1], z_j(t) = g_j(t) − δ·p_j(t) + δ, with g_j and p_j the shares of its
    detections that are placed and gross, and placed (score ≤ t): E[z] ≤ δ exactly when the
    expected gross share among placed detections, positions weighted equally, is ≤ δ. For each
    candidate threshold (``n_candidates`` quantiles of the scores) the null E[z] ≥ δ is tested with
    a betting p-value over the n positions (``betting_p_value``) at level ε / ``n_candidates`` (Bonferroni:
    the risk is not monotone in t, so no fixed testing order is known to be favourable; Learn then
    Test, Angelopoulos et al. 2021), and the most permissive rejected threshold is returned. The
    certificate needs many positions, the more the smaller δ.

    Parameters
    ----------
    score, gross, groups : numpy.ndarray
        (n,) calibration scores, gross flags and positions.
    delta, epsilon : float
        Tolerated gross share among placed detections, and probability that the guarantee fails.
    n_candidates : int
        Candidate thresholds tested.

    Returns
    -------
    threshold : float
        −inf when no threshold can be certified.
    path : list of dict
        ``threshold, n_placed, n_gross, mean_loss, p_value`` of every candidate.
    """
    if not 0 < delta < 1 or not 0 < epsilon < 1:
        raise ValueError(f"selective delta and epsilon must lie in (0, 1); got {delta}, {epsilon}")
    score, gross, groups = np.asarray(score, dtype=float), np.asarray(gross, dtype=bool), np.asarray(groups)
    _, inverse, counts = np.unique(groups, return_inverse=True, return_counts=True)
    n = counts.size
    weight = 1.0 / counts[inverse]  # each detection's share of its position
    finite = score[np.isfinite(score)]
    candidates = np.unique(np.quantile(finite, np.linspace(0, 1, n_candidates + 1)[1:])) if finite.size else np.array([])
    threshold, path = -math.inf, []
    for t in candidates:
        placed = score <= t
        placed_share = np.bincount(inverse, weights=weight * placed, minlength=n)
        gross_share = np.bincount(inverse, weights=weight * (placed & gross), minlength=n)
        z = gross_share - delta * placed_share + delta
        mean_loss = float(np.mean(z))
        p_value = betting_p_value(z, delta, epsilon / len(candidates))
        path.append(
            {
                "threshold": float(t),
                "n_placed": int(placed.sum()),
                "n_gross": int((placed & gross).sum()),
                "mean_loss": mean_loss,
                "p_value": p_value,
            }
        )
        if p_value <= epsilon / len(candidates):
            threshold = max(threshold, float(t))
    return threshold, path


def check_calibration_unit(unit: str, method: str = "pooled") -> None:
    """Refuse a calibration unit or position method the scorers do not know (one line naming the value)."""
    if unit not in CALIBRATION_UNITS:
        raise ConfigError(f"conformal calibration_unit must be 'event' or 'position'; got {unit!r}")
    if method not in POSITION_METHODS:
        raise ConfigError(f"conformal position_method must be 'pooled', 'subsample' or 'pac'; got {method!r}")


def calibration_quantile(
    scores: np.ndarray,
    level: float,
    unit: str = "event",
    groups: np.ndarray | None = None,
    method: str = "pooled",
    seed: int = 0,
    pac: tuple[float, float] = (0.1, 0.05),
) -> float:
    """The conformal quantile of ``scores`` whose guarantee is over ``unit``: events, or positions (``groups``) by ``method``.

    ``event``: ``conformal_quantile``; ``position``: ``grouped_conformal_quantile`` (``pooled``),
    ``subsampled_position_quantile`` (``subsample``, one event per position drawn with ``seed``), or
    the same draw at the PAC rank for ``pac = (delta, epsilon)`` (``pac``).
    """
    if unit == "event":
        return conformal_quantile(scores, level)
    if groups is None:
        raise ValueError("calibration_unit='position' needs the calibration events' positions (groups)")
    if method == "pooled":
        return grouped_conformal_quantile(scores, np.asarray(groups), level)
    return subsampled_position_quantile(scores, np.asarray(groups), level, seed, pac if method == "pac" else None)
