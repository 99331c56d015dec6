"""The consistent-set candidate selection of :mod:`plugins.solvers.consistent_set`, compiled per event (numba).

:meth:`plugins.solvers.consistent_set.ConsistentSetSolver.select` in numpy builds each event's
pair tables, scores the hypotheses with a sparse product and fits the arrival times with batched
normal equations: some 150 numpy calls per chunk of 16 events, about 75 µs per 6-mic event on one
core, most of it call overhead on small arrays. :func:`select_compiled` does the same work event
by event in compiled loops (``solver=consistent_set_compiled``):

* the pair tables and their −inf entries for missing arrival times, as numpy builds them;
* the same winner and runner-up: each hypothesis' raw score is summed in pair order from 0 and its
  lateness as numpy's pairwise reduction sums it, so the scores are the numpy scores, bit for bit.
  They are found by one exact branch and bound (:func:`_collect`) that keeps every hypothesis
  scoring at least a certified lower bound on the runner-up's score (the runner-up: the best pattern
  more than the tolerance from the winner's), so only a few dozen hypotheses are scored in full;
  where more would have to be kept (many near-ties), by two (:func:`_winner`: the winner, then the
  runner-up);
* the trusted mics, the chosen lags and the least-squares arrival times, solved by Gaussian
  elimination with partial pivoting in place of LAPACK: the times agree with numpy's to rounding
  (~10⁻¹⁶ s), not bit for bit.

Written by hand: the search is a bounded enumeration over a dense pairwise score that no library
offers, and the per-event linear algebra is 6 × 6, where a LAPACK call costs more than the solve.
The kernels are cached beside this module (``cache=True``): compiled once per installation (a few
seconds), loaded by the first compiled solve of a process (about 0.6 s with numba's import).
"""

from __future__ import annotations

import functools

import numba
import numpy as np

from plugins.solvers.hypothesis_search import LATENESS_WEIGHT, pair_layout

#: Diagnostics returned per event, in this order (see :class:`plugins.solvers.consistent_set.ConsistentSetSolver`).
DIAGNOSTICS = ("consistent_pairs", "consistency", "score_margin", "n_mics_used", "closure_rms_s")

_BIG = np.finfo(np.float64).max
#: Hypotheses the one-pass search may keep per event before it falls back to two passes.
_KEPT = 256


def select_compiled(candidates_s: np.ndarray, weights: np.ndarray, prior_lags_s: np.ndarray | None, *, k: int, tolerance_s: float,
                    prior_weight: float, prior_tolerance_s: float) -> dict[str, np.ndarray]:
    """The consistent set of every event, as :meth:`ConsistentSetSolver.select` returns it (module docstring).

    Parameters
    ----------
    candidates_s : numpy.ndarray
        (B, P, K) candidate lags t_j − t_i per pair (i < j, the project's pair order), s; NaN where a pair has fewer peaks.
    weights : numpy.ndarray
        (B, P, K) GCC heights of the candidates (NaN counts as 0).
    prior_lags_s : numpy.ndarray or None
        (B, P) pair lags an independent estimate implies, s (None: no prior term).
    k : int
        Candidates per pair that form hypotheses (≤ K; every K candidates still count for consistency).
    tolerance_s, prior_weight, prior_tolerance_s : float
        As the solver's parameters of the same names.

    Returns
    -------
    dict
        ``times_s`` (B, M), ``trusted`` (B, M) and the :data:`DIAGNOSTICS` (B,).
    """
    cands = np.ascontiguousarray(candidates_s, dtype=np.float64)
    bsz, n_pairs, k_all = cands.shape
    m = int(round((1 + np.sqrt(1 + 8 * n_pairs)) / 2))
    layout = pair_layout(m)
    if len(layout.i_idx) != n_pairs or not 1 <= k <= k_all:
        raise ValueError(f"select_compiled needs the candidates of all pairs of M mics and 1 <= k <= K; got {n_pairs} pairs, k={k}, K={k_all}")
    wgt = np.ascontiguousarray(np.broadcast_to(weights, cands.shape), dtype=np.float64)
    use_prior = prior_lags_s is not None and prior_weight > 0
    prior = np.ascontiguousarray(prior_lags_s if use_prior else np.zeros((bsz, n_pairs)), dtype=np.float64)
    i_idx, j_idx, pair_index, mic_of_slot = _layout(m)
    times = np.empty((bsz, m))
    trusted = np.empty((bsz, m), dtype=np.bool_)
    diagnostics = np.empty((bsz, len(DIAGNOSTICS)))
    _select(cands, wgt, prior, use_prior, float(prior_weight), float(prior_tolerance_s), float(tolerance_s), int(k),
            i_idx, j_idx, pair_index, mic_of_slot, LATENESS_WEIGHT, times, trusted, diagnostics)
    return {"times_s": times, "trusted": trusted, **{name: diagnostics[:, n] for n, name in enumerate(DIAGNOSTICS)}}


@functools.lru_cache(maxsize=32)
def _layout(n_mics: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`pair_layout`'s index arrays as int64 (the kernel's types), once per array size."""
    layout = pair_layout(n_mics)
    arrays = tuple(np.ascontiguousarray(a, dtype=np.int64) for a in (layout.i_idx, layout.j_idx, layout.pair_index, layout.mic_of_slot))
    for array in arrays:
        array.setflags(write=False)
    return arrays


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _numpy_max(a, b):
    # np.maximum: the first argument where a >= b or a is NaN
    return a if (a >= b or np.isnan(a)) else b


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _clean_weight(w):
    # np.nan_to_num: NaN → 0, ±inf → ±largest float
    if np.isnan(w):
        return 0.0
    if w == np.inf:
        return _BIG
    if w == -np.inf:
        return -_BIG
    return w


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _lateness(t, m, late):
    """Σ (t − min t) as numpy's reduction over the last axis sums it (its pairwise sum: sequential from −0.0
    below 8 terms, eight accumulators in blocks of 8 up to 128); ``late`` receives the terms."""
    lo = t[0]
    for n in range(1, m):
        if np.isnan(t[n]) or t[n] < lo:  # NaN propagates, as numpy's min
            lo = t[n]
    for n in range(m):
        late[n] = t[n] - lo
    if m < 8:
        s = -0.0
        for n in range(m):
            s += late[n]
        return s
    r0, r1, r2, r3 = late[0], late[1], late[2], late[3]
    r4, r5, r6, r7 = late[4], late[5], late[6], late[7]
    n = 8
    while n + 8 <= m:
        r0 += late[n]
        r1 += late[n + 1]
        r2 += late[n + 2]
        r3 += late[n + 3]
        r4 += late[n + 4]
        r5 += late[n + 5]
        r6 += late[n + 6]
        r7 += late[n + 7]
        n += 8
    s = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while n < m:
        s += late[n]
        n += 1
    return s


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _final(raw, lateness, weight):
    if np.isnan(lateness):
        lateness = 1e3
    elif lateness == np.inf:
        lateness = _BIG
    return raw - weight * lateness


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _solve_in_place(a, b, m):
    """Solve a x = b (m × m) by Gaussian elimination with partial pivoting; x overwrites b."""
    for col in range(m):
        piv = col
        for row in range(col + 1, m):
            if abs(a[row, col]) > abs(a[piv, col]):
                piv = row
        if piv != col:
            for n in range(m):
                a[col, n], a[piv, n] = a[piv, n], a[col, n]
            b[col], b[piv] = b[piv], b[col]
        for row in range(col + 1, m):
            f = a[row, col] / a[col, col]
            for n in range(col, m):
                a[row, n] -= f * a[col, n]
            b[row] -= f * b[col]
    for row in range(m - 1, -1, -1):
        s = b[row]
        for n in range(row + 1, m):
            s -= a[row, n] * b[n]
        b[row] = s / a[row, row]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _score(table, arrival, r, rank, m, n_pairs, i_idx, j_idx, t, late, lateness_weight):
    """The final score of hypothesis (r, rank) as the numpy search computes it; its arrival times land in t."""
    raw = 0.0
    for p in range(n_pairs):
        raw += table[r, p, rank[i_idx[p]], rank[j_idx[p]]]
    for n in range(m):
        t[n] = arrival[r, n, rank[n]]
    return _final(raw, _lateness(t, m, late), lateness_weight)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _deviation(t, ref_t, m):
    """Largest |(t_n − t_0) − (ref_n − ref_0)|, s (NaN where a time is NaN, as numpy's max)."""
    dev = abs(t[0] - t[0] - (ref_t[0] - ref_t[0]))
    for n in range(1, m):
        dev = _numpy_max(dev, abs(t[n] - t[0] - (ref_t[n] - ref_t[0])))
    return dev


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _root_bound(best_given_i, best_given_j, best_pair, r, n_pairs, i_idx, j_idx, bound_at, time_sum, time_min):
    """The bound of reference r's root (only the reference fixed, at rank 0) into depth 0 of the per-depth scratch."""
    root = 0.0
    for p in range(n_pairs):
        if i_idx[p] == r:
            root += best_given_i[r, p, 0]
        elif j_idx[p] == r:
            root += best_given_j[r, p, 0]
        else:
            root += best_pair[r, p]
    bound_at[0], time_sum[0], time_min[0] = root, 0.0, 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _child_bound(table, best_given_i, best_given_j, best_pair, arrival, r, rank, depth, m, i_idx, j_idx, pair_index,
                 bound_at, time_sum, time_min):
    """The node just reached fixes mic n (slot depth − 1) on top of its parent: its bound is the parent's plus the change
    in n's pairs, and its fixed mics' time sum and earliest time (for the lateness penalty's floor), into depth ``depth``."""
    n = depth - 1 + (depth - 1 >= r)  # slot s of reference r is mic s + (s ≥ r)
    q = rank[n]
    bound = bound_at[depth - 1]
    for x in range(m):
        if x == n:
            continue
        p = pair_index[n, x]
        if x == r or x - (x > r) < depth - 1:  # x fixed: the pair's entry replaces its best given x's rank
            new = table[r, p, rank[i_idx[p]], rank[j_idx[p]]]
            old = best_given_i[r, p, rank[x]] if x < n else best_given_j[r, p, rank[x]]
        else:  # x free: the best given n's rank replaces the pair's best
            new = best_given_i[r, p, q] if n < x else best_given_j[r, p, q]
            old = best_pair[r, p]
        bound += new - old
    bound_at[depth] = bound
    v = arrival[r, n, q]
    time_sum[depth] = time_sum[depth - 1] + v
    time_min[depth] = min(time_min[depth - 1], v)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _search(table, best_given_i, best_given_j, best_pair, arrival, k, m, n_pairs, i_idx, j_idx, pair_index, mic_of_slot, lateness_weight,
            rank, t, late, win_t, tol, runner_up, start, bound_at, time_sum, time_min):
    """Branch and bound over every reference's slot ranks, depth first in index order.

    A node fixes the reference and slots 0 … d − 1. Its bound on the raw score of every hypothesis
    below it is the sum over pairs of the pair's entry where both mics are fixed, its largest entry
    given the fixed mic's rank where one is, and its largest entry where neither is; a child's bound
    is its parent's plus the change in the pairs of the mic it fixes. Less the smallest lateness
    penalty its fixed mics already imply (the earliest of all mics is no later than the earliest
    fixed one, and free mics add ≥ 0), that bounds every final score below the node. A subtree is
    skipped when it lies below the best score found so far by more than rounding (10⁻¹² relative):
    nothing in it could replace the best, which only a strictly higher exact score does (keeping
    the first in index order). Leaves are scored exactly as the numpy search scores them.

    Returns (best final score, its reference, its slot code) of the winner (``runner_up`` False:
    the first highest) or of the runner-up (True: the highest among patterns more than ``tol``
    from ``win_t``); (``start``, −1, −1) when no hypothesis scores above ``start``, a score already
    reached by an eligible hypothesis (−inf for the winner's search). ``bound_at``, ``time_sum``,
    ``time_min`` (M,): scratch per depth.
    """
    n_slots = m - 1
    best, best_r, best_code = start, -1, -1
    for r in range(m):
        for n in range(m):
            rank[n] = 0
        _root_bound(best_given_i, best_given_j, best_pair, r, n_pairs, i_idx, j_idx, bound_at, time_sum, time_min)
        depth = 0  # the node: slots 0 … depth − 1 fixed at their ranks; free slots hold rank 0
        while True:
            if depth > 0:
                _child_bound(table, best_given_i, best_given_j, best_pair, arrival, r, rank, depth, m, i_idx, j_idx, pair_index,
                             bound_at, time_sum, time_min)
            bound = bound_at[depth]
            lateness = max(time_sum[depth] - (depth + 1) * time_min[depth], 0.0)
            if bound > -np.inf and bound - lateness_weight * lateness >= best - 1e-12 * (1.0 + abs(best)):
                if depth < n_slots:
                    depth += 1
                    continue
                score = _score(table, arrival, r, rank, m, n_pairs, i_idx, j_idx, t, late, lateness_weight)
                if score > best and (not runner_up or _deviation(t, win_t, m) > tol):
                    best, best_r, best_code = score, r, 0
                    for s in range(n_slots):
                        best_code = best_code * k + rank[mic_of_slot[r, s]]
            # next sibling of the node, or of its nearest ancestor that has one
            while depth > 0:
                mic = mic_of_slot[r, depth - 1]
                if rank[mic] + 1 < k:
                    rank[mic] += 1
                    break
                rank[mic] = 0
                depth -= 1
            if depth == 0:
                break
    return best, best_r, best_code


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _tables(cands, w, prior, use_prior, prior_weight, prior_tol, tol, k, i_idx, j_idx, pair_index, pair_lag, lag_w,
            arrival, table, best_given_i, best_given_j, best_pair):
    """One event's candidate arrival times (R, M, k) and pair tables (R, P, k, k), as numpy builds them, and the
    tables' largest entries given the first mic's rank, the second's (R, P, k), and overall (R, P) for the bounds."""
    n_pairs, k_all = cands.shape
    m = arrival.shape[0]
    for r in range(m):
        for n in range(m):
            for a in range(k):
                if n == r:
                    arrival[r, n, a] = 0.0
                elif r < n:
                    arrival[r, n, a] = cands[pair_index[r, n], a]
                else:
                    arrival[r, n, a] = -cands[pair_index[r, n], a]
    for r in range(m):
        for p in range(n_pairs):
            i, j = i_idx[p], j_idx[p]
            for rr in range(k_all):
                pair_lag[rr] = cands[p, rr]
                lag_w[rr] = w[p, rr]
            for a in range(k):
                best_given_i[r, p, a] = best_given_j[r, p, a] = -np.inf
            for a in range(k):
                ai = arrival[r, i, a]
                finite_i = np.isfinite(ai)
                for c in range(k):
                    aj = arrival[r, j, c]
                    if not (finite_i and np.isfinite(aj)):
                        val = -np.inf  # a missing arrival time
                    else:
                        pred = aj - ai
                        # numpy's running np.maximum from 0 of close · weight (≥ 0 throughout: a far candidate adds nothing)
                        val = 0.0
                        for rr in range(k_all):
                            val = max(val, lag_w[rr] if abs(pred - pair_lag[rr]) < tol else 0.0)
                        if use_prior and abs(pred - prior[p]) < prior_tol:
                            val = val + prior_weight
                    table[r, p, a, c] = val
                    best_given_i[r, p, a] = max(best_given_i[r, p, a], val)
                    best_given_j[r, p, c] = max(best_given_j[r, p, c], val)
            best = -np.inf
            for a in range(k):
                best = max(best, best_given_i[r, p, a])
            best_pair[r, p] = best


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _trust_and_fit(cands, tol, win_t, i_idx, j_idx, gap_ok, chosen, per_mic, normal, rhs, times_out, trusted_out, diag):
    """The mics to trust given the winner's arrival times, the least-squares times of the trusted mics from the chosen
    lags of their consistent pairs (sum of times 0), and the consistency diagnostics (numpy's ``select``, event by event)."""
    n_pairs, k_all = cands.shape
    m = win_t.shape[0]
    n_ok = 0
    per_mic[:] = 0.0
    for p in range(n_pairs):
        i, j = i_idx[p], j_idx[p]
        predicted = win_t[j] - win_t[i]
        best_gap, best_rank = np.inf, 0
        gap_ok[p] = False
        for rr in range(k_all):
            gap = abs(cands[p, rr] - predicted)
            gap_ok[p] |= gap < tol
            if gap < best_gap:  # NaN gaps are never chosen
                best_gap, best_rank = gap, rr
        chosen[p] = cands[p, best_rank]
        if gap_ok[p]:
            n_ok += 1
            per_mic[i] += 1.0
            per_mic[j] += 1.0
    need = min(2.0, m - 1.0)
    n_trusted = 0
    for n in range(m):
        trusted_out[n] = per_mic[n] >= need
        n_trusted += trusted_out[n]
    if n_trusted < 3:  # with fewer than three trusted mics keep them all (and say so via consistency)
        trusted_out[:] = True
        n_trusted = m
    n_use = n_pair_trusted = 0
    rhs[:] = 0.0
    per_mic[:] = 0.0  # now: used pairs per mic
    normal[:, :] = 0.0
    for p in range(n_pairs):
        i, j = i_idx[p], j_idx[p]
        both = trusted_out[i] and trusted_out[j]
        n_pair_trusted += both
        if both and gap_ok[p]:
            n_use += 1
            normal[i, i] += 1.0
            normal[j, j] += 1.0
            normal[i, j] -= 1.0
            normal[j, i] -= 1.0
            rhs[i] -= chosen[p]
            rhs[j] += chosen[p]
            per_mic[i] += 1.0
            per_mic[j] += 1.0
    normal += 1.0 / m  # the pairs' incidence first, then the sum-of-times row (as numpy adds them)
    mean, n_finite = 0.0, 0
    for n in range(m):
        if not np.isnan(win_t[n]):
            mean += win_t[n]
            n_finite += 1
    for n in range(m):
        if per_mic[n] == 0.0:  # a mic with no used pair keeps the hypothesis' time (it is not trusted anyway)
            normal[n, n] += 1.0
            shift = win_t[n] - mean / n_finite
            rhs[n] += shift if np.isfinite(shift) else 0.0
    _solve_in_place(normal, rhs, m)
    closure = 0.0
    for p in range(n_pairs):
        i, j = i_idx[p], j_idx[p]
        if trusted_out[i] and trusted_out[j] and gap_ok[p]:
            closure += ((rhs[j] - rhs[i]) - chosen[p]) ** 2
    for n in range(m):
        times_out[n] = rhs[n] if trusted_out[n] else np.nan
    diag[0] = n_ok
    diag[1] = n_use / max(n_pair_trusted, 1)
    diag[3] = n_trusted
    diag[4] = np.sqrt(closure / n_use) if n_use > 0 else np.nan


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _winner(table, best_given_i, best_given_j, best_pair, arrival, k, i_idx, j_idx, pair_index, mic_of_slot, lateness_weight, tol,
            scratch, rank, win_t):
    """The winner's arrival times into win_t and the score margin over the runner-up (NaN without one)."""
    m, n_pairs = table.shape[0], table.shape[1]
    t, late, bound_at, time_sum, time_min = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4]
    # pass 1: the winner, the first hypothesis in index order with the highest final score
    win_score, r, code = _search(table, best_given_i, best_given_j, best_pair, arrival, k, m, n_pairs, i_idx, j_idx, pair_index,
                                 mic_of_slot, lateness_weight, rank, t, late, win_t, tol, False, -np.inf, bound_at, time_sum, time_min)
    if not win_score > -np.inf:  # every hypothesis misses an arrival time: the first hypothesis (reference 0, ranks 0)
        for n in range(m):
            win_t[n] = arrival[0, n, 0]
        return np.nan
    rank[r] = 0
    for s in range(m - 2, -1, -1):
        rank[mic_of_slot[r, s]] = code % k
        code //= k
    for n in range(m):
        win_t[n] = arrival[r, n, rank[n]]
    # pass 2: the runner-up, the best final score of a pattern more than the tolerance from the winner's;
    # the winner's one-slot variants give it a score to prune from (often the runner-up's own)
    start = -np.inf
    for s in range(m - 1):
        mic = mic_of_slot[r, s]
        own = rank[mic]
        for q in range(k):
            if q != own:
                rank[mic] = q
                score = _score(table, arrival, r, rank, m, n_pairs, i_idx, j_idx, t, late, lateness_weight)
                if score > start and _deviation(t, win_t, m) > tol:
                    start = score
        rank[mic] = own
    runner = _search(table, best_given_i, best_given_j, best_pair, arrival, k, m, n_pairs, i_idx, j_idx, pair_index, mic_of_slot,
                     lateness_weight, rank, t, late, win_t, tol, True, start, bound_at, time_sum, time_min)[0]
    return win_score - runner if np.isfinite(runner) else np.nan


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _collect(table, best_given_i, best_given_j, best_pair, arrival, k, i_idx, j_idx, pair_index, lateness_weight, far, theta,
             rank, scratch, kept_score, kept_times):
    """Every hypothesis that can be the winner or the runner-up, in one branch and bound, in index order.

    ``theta`` is a certified lower bound on the runner-up's final score (and so on the winner's):
    the lower score of two scored hypotheses whose patterns lie more than ``far`` (twice the
    tolerance) apart, one of which is more than the tolerance from the winner's, whichever it is
    (the pattern distance obeys the triangle inequality). Subtrees whose bound (see :func:`_search`)
    lies below θ by more than rounding are skipped; every leaf scoring ≥ θ is kept (score and
    arrival times), and θ rises as kept leaves form new far-apart pairs. Returns the number kept,
    −1 when more than ``kept_score``'s length would be.
    """
    m, n_pairs = table.shape[0], table.shape[1]
    n_slots = m - 1
    t, late, bound_at, time_sum, time_min = scratch[0], scratch[1], scratch[2], scratch[3], scratch[4]
    n_kept = 0
    for r in range(m):
        for n in range(m):
            rank[n] = 0
        _root_bound(best_given_i, best_given_j, best_pair, r, n_pairs, i_idx, j_idx, bound_at, time_sum, time_min)
        depth = 0
        while True:
            if depth > 0:
                _child_bound(table, best_given_i, best_given_j, best_pair, arrival, r, rank, depth, m, i_idx, j_idx, pair_index,
                             bound_at, time_sum, time_min)
            bound = bound_at[depth]
            lateness = max(time_sum[depth] - (depth + 1) * time_min[depth], 0.0)
            floor = theta - 1e-12 * (1.0 + abs(theta))
            if bound > -np.inf and bound - lateness_weight * lateness >= floor:
                if depth < n_slots:
                    depth += 1
                    continue
                score = _score(table, arrival, r, rank, m, n_pairs, i_idx, j_idx, t, late, lateness_weight)
                if score > -np.inf and score >= floor:
                    if n_kept == kept_score.shape[0]:
                        return -1, theta
                    for y in range(n_kept):
                        if _deviation(t, kept_times[y], m) > far:
                            theta = max(theta, min(score, kept_score[y]))
                    kept_score[n_kept] = score
                    kept_times[n_kept, :] = t
                    n_kept += 1
            while depth > 0:
                mic = depth - 1 + (depth - 1 >= r)
                if rank[mic] + 1 < k:
                    rank[mic] += 1
                    break
                rank[mic] = 0
                depth -= 1
            if depth == 0:
                break
    return n_kept, theta


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _winner_one_pass(table, best_given_i, best_given_j, best_pair, arrival, k, i_idx, j_idx, pair_index, mic_of_slot, lateness_weight,
                     tol, scratch, rank, win_t, kept_score, kept_times):
    """:func:`_winner` in one branch and bound (:func:`_collect`) where the hypotheses it keeps fit the buffers, else in two.

    θ starts from reference 0's hypothesis of top-ranked lags and its one-slot variants: the lower
    score of it and any variant whose pattern lies more than twice the tolerance from it.
    """
    m, n_pairs = table.shape[0], table.shape[1]
    t, late, base = scratch[0], scratch[1], scratch[2]
    far = 2 * tol * (1 + 1e-9) + 1e-15  # a hair over twice the tolerance, for rounding
    rank[:] = 0
    first = _score(table, arrival, 0, rank, m, n_pairs, i_idx, j_idx, t, late, lateness_weight)
    base[:] = t
    theta = -np.inf
    for s in range(m - 1):
        mic = mic_of_slot[0, s]
        for q in range(1, k):
            rank[mic] = q
            score = _score(table, arrival, 0, rank, m, n_pairs, i_idx, j_idx, t, late, lateness_weight)
            if _deviation(t, base, m) > far:
                theta = max(theta, min(first, score))
        rank[mic] = 0
    n_kept, theta = _collect(table, best_given_i, best_given_j, best_pair, arrival, k, i_idx, j_idx, pair_index, lateness_weight, far,
                             theta, rank, scratch, kept_score, kept_times)
    if n_kept < 0:  # more candidates than the buffers hold (many near-ties): two passes
        return _winner(table, best_given_i, best_given_j, best_pair, arrival, k, i_idx, j_idx, pair_index, mic_of_slot,
                       lateness_weight, tol, scratch, rank, win_t)
    win = -1
    for h in range(n_kept):  # the first highest, in index order
        if win < 0 or kept_score[h] > kept_score[win]:
            win = h
    if win < 0:  # every hypothesis misses an arrival time: the first hypothesis (reference 0, ranks 0)
        for n in range(m):
            win_t[n] = arrival[0, n, 0]
        return np.nan
    win_t[:] = kept_times[win]
    runner = -np.inf
    for h in range(n_kept):
        if kept_score[h] > runner and _deviation(kept_times[h], win_t, m) > tol:
            runner = kept_score[h]
    return kept_score[win] - runner if np.isfinite(runner) else np.nan


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _select(cands, weights, prior, use_prior, prior_weight, prior_tol, tol, k, i_idx, j_idx, pair_index, mic_of_slot, lateness_weight,
            times_out, trusted_out, diag_out):
    bsz, n_pairs, k_all = cands.shape
    m = times_out.shape[1]
    w = np.empty((n_pairs, k_all))
    pair_lag, lag_w = np.empty(k_all), np.empty(k_all)
    arrival = np.empty((m, m, k))
    table = np.empty((m, n_pairs, k, k))
    best_given_i, best_given_j = np.empty((m, n_pairs, k)), np.empty((m, n_pairs, k))
    best_pair = np.empty((m, n_pairs))
    rank = np.zeros(m, np.int64)
    scratch = np.empty((5, m))
    kept_score, kept_times = np.empty(_KEPT), np.empty((_KEPT, m))
    win_t = np.empty(m)
    gap_ok = np.empty(n_pairs, np.bool_)
    chosen = np.empty(n_pairs)
    per_mic, rhs = np.empty(m), np.empty(m)
    normal = np.empty((m, m))
    for b in range(bsz):
        for p in range(n_pairs):
            for rr in range(k_all):
                w[p, rr] = _clean_weight(weights[b, p, rr]) if np.isfinite(cands[b, p, rr]) else 0.0
        _tables(cands[b], w, prior[b], use_prior, prior_weight, prior_tol, tol, k, i_idx, j_idx, pair_index, pair_lag, lag_w,
                arrival, table, best_given_i, best_given_j, best_pair)
        diag_out[b, 2] = _winner_one_pass(table, best_given_i, best_given_j, best_pair, arrival, k, i_idx, j_idx, pair_index, mic_of_slot,
                                          lateness_weight, tol, scratch, rank, win_t, kept_score, kept_times)
        _trust_and_fit(cands[b], tol, win_t, i_idx, j_idx, gap_ok, chosen, per_mic, normal, rhs, times_out[b], trusted_out[b], diag_out[b])
