"""The consistent-set candidate selection of :mod:`plugins.solvers.consistent_set`, compiled per event (numba).

:meth:`plugins.solvers.consistent_set.ConsistentSetSolver.select` in numpy builds each event's
pair tables, scores the hypotheses with a sparse product and fits the arrival times with batched
normal equations: some 150 numpy calls per chunk of 16 events, about 75 µs per 6-mic event on one
core, most of it call overhead on small arrays. :func:`select_compiled` does the same work event
by event in compiled loops (``solver=consistent_set_compiled``):

* the pair tables and their −inf entries for missing arrival times, as numpy builds them, but
  those of the pairs with the reference once per pair (:func:`_tables`; their predicted lag is the
  candidate itself);
* the same winner and runner-up: each hypothesis' raw score is summed in pair order from 0 and its
  lateness as numpy's pairwise reduction sums it, so the scores are the numpy scores, bit for bit.
  They are found by one exact branch and bound (:func:`_branch_and_bound`) that keeps every
  hypothesis scoring at least a certified lower bound on the runner-up's score (the runner-up: the
  best pattern more than the tolerance from the winner's), so only a few dozen hypotheses are
  scored in full; where more would have to be kept (many near-ties), by two (:func:`_winner`: the
  winner, then the runner-up). A node's bound takes, for each free mic, its best rank given every
  fixed mic at once (not pair by pair), which cuts more of the tree than per-pair maxima;
* the trusted mics, the chosen lags and the least-squares arrival times, solved by Gaussian
  elimination with partial pivoting in place of LAPACK: the times agree with numpy's to rounding
  (~10⁻¹⁶ s), not bit for bit.

Written by hand: the search is a bounded enumeration over a dense pairwise score that no library
offers, and the per-event linear algebra is 6 × 6, where a LAPACK call costs more than the solve.
The per-event work is inlined into one loop (``inline="always"``: the tables, the one-pass search
and its branch and bound, the fit), arrays are indexed rather than sliced, and each event's rows
are copied in and out by index: about 15 % less time per 6-mic event than the same work in calls
(same choices, bit for bit), measured. The reference counts a call or a view takes (atomic
operations) are not where that time went: compiled without them (numba's ``_nrt=False``) the loop
ran no faster. Only the rare two-pass search (:func:`_winner`) is a call. With three candidates
per pair (the default) the pair tables and each candidate's own entry are computed for
:data:`LANES` events at once, the events innermost, which the compiler turns into vector
instructions (:func:`_lane_tables`: every entry by the one formula :func:`_entry_of_three`, so the
same tables bit for bit), and each event copies its own out. In alternating timings on the
solver_speed detections the lanes' pair tables took 0–6 % less time per 6-mic event than building
each event's on its own, and their own entries (no per-event weights then) made the selection
1.07–1.10× faster again: about 3.3 µs per event, of which the branch and bound takes about 2.3.
The kernels are cached beside this module (``cache=True``): compiled once per installation (about
30 s on one core: one large inlined function), loaded by the first compiled solve of a process
(about 0.6 s with numba's import).
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
    i_idx, j_idx, ref_pair, slot_pair = _layout(m)
    times = np.empty((bsz, m))
    trusted = np.empty((bsz, m), dtype=np.bool_)
    diagnostics = np.empty((bsz, len(DIAGNOSTICS)))
    _select(cands, wgt, prior, use_prior, float(prior_weight), float(prior_tolerance_s), float(tolerance_s), int(k), int(k_all),
            i_idx, j_idx, ref_pair, slot_pair, LATENESS_WEIGHT, times, trusted, diagnostics)
    return {"times_s": times, "trusted": trusted, **{name: diagnostics[:, n] for n, name in enumerate(DIAGNOSTICS)}}


@functools.lru_cache(maxsize=32)
def _layout(n_mics: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kernel's index arrays, once per array size: :func:`pair_layout`'s ``i_idx`` and ``j_idx`` (P,), the pair of
    reference r and slot s (R, S) (int64), and the pair of slots s and s2 under reference r (R, S, S; uint64, as the
    innermost loops index with it), where slot s of reference r is mic s + (s ≥ r)."""
    layout = pair_layout(n_mics)
    slot_mic = layout.mic_of_slot
    ref_pair = layout.pair_index[np.arange(n_mics)[:, None], slot_mic]
    slot_pair = layout.pair_index[slot_mic[:, :, None], slot_mic[:, None, :]]
    arrays = tuple(np.ascontiguousarray(a, dtype=np.int64) for a in (layout.i_idx, layout.j_idx, ref_pair)) + (
        np.ascontiguousarray(slot_pair, dtype=np.uint64),)  # unsigned: indexing with it needs no negative-index wraparound
    for array in arrays:
        array.setflags(write=False)
    return arrays


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _numpy_max(a, b):
    # np.maximum: the first argument where a >= b or a is NaN
    return a if (a >= b or np.isnan(a)) else b


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _clean_weight(w, lag):
    """The weight a candidate at ``lag`` counts with: 0 where the lag is missing (not finite), else its height as
    np.nan_to_num cleans it (NaN → 0, ±inf → ±largest float)."""
    if not np.isfinite(lag) or np.isnan(w):
        return 0.0
    if w == np.inf:
        return _BIG
    if w == -np.inf:
        return -_BIG
    return w


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
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


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _final(raw, lateness, weight):
    if np.isnan(lateness):
        lateness = 1e3
    elif lateness == np.inf:
        lateness = _BIG
    return raw - weight * lateness


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
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


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _arrival(lag, first):
    """A pair's other mic's arrival time relative to the reference, s, from the pair's lag t_j − t_i: the lag where the
    reference is the pair's first mic i, its negative where it is the second."""
    return lag if first else -lag


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _entry(pred, cands, w, p, k_all, tol, use_prior, prior_lag, prior_weight, prior_tol):
    """One pair-table entry of pair p for a predicted lag, as numpy computes it: the running np.maximum from 0 of
    close · weight over the pair's candidates (≥ 0 throughout), plus the prior's weight where it agrees."""
    val = 0.0
    for rr in range(k_all):
        val = max(val, w[p, rr] if abs(pred - cands[p, rr]) < tol else 0.0)
    if use_prior and abs(pred - prior_lag) < prior_tol:
        val = val + prior_weight
    return val


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _entry_of_three(pred, l0, l1, l2, w0, w1, w2, tol, use_prior, prior_lag, prior_weight, prior_tol):
    """:func:`_entry` of a pair with three candidates (lags l0 … l2, s; cleaned weights w0 … w2) spelled out: the same
    operations in the same order (the running maximum from 0, then the prior's weight), so the same value bit for bit;
    the one formula of the per-event tables (:func:`_pair_table`) and the lanes' (:func:`_lane_tables`)."""
    val = max(max(max(0.0, w0 if abs(pred - l0) < tol else 0.0), w1 if abs(pred - l1) < tol else 0.0), w2 if abs(pred - l2) < tol else 0.0)
    if use_prior and abs(pred - prior_lag) < prior_tol:
        val = val + prior_weight
    return val


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _pair_table(cands, w, p, k_all, arrival, r, s, s2, k, tol, use_prior, prior_lag, prior_weight, prior_tol, table):
    """Pair p's table ``table[r, p]`` (k, k) under reference r for the candidate arrival times of its first and second
    mic, slots s and s2 (``arrival[r, s]``, ``arrival[r, s2]``), −inf where one is missing (``x − x == 0`` tests that x
    is finite); returns its largest entry. With three candidates (the default) they are held in registers, the same
    entries in the same order. Arrays are indexed, not sliced: a view costs atomic reference counts."""
    three = k_all == 3
    l0, l1, l2 = (cands[p, 0], cands[p, 1], cands[p, 2]) if three else (0.0, 0.0, 0.0)
    w0, w1, w2 = (w[p, 0], w[p, 1], w[p, 2]) if three else (0.0, 0.0, 0.0)
    top = -np.inf
    for a in range(k):
        ai = arrival[r, s, a]
        finite = ai - ai == 0.0
        for c in range(k):
            aj = arrival[r, s2, c]
            if not (finite and aj - aj == 0.0):
                val = -np.inf  # a missing arrival time
            elif three:
                val = _entry_of_three(aj - ai, l0, l1, l2, w0, w1, w2, tol, use_prior, prior_lag, prior_weight, prior_tol)
            else:
                val = _entry(aj - ai, cands, w, p, k_all, tol, use_prior, prior_lag, prior_weight, prior_tol)
            table[r, p, a, c] = val
            top = max(top, val)
    return top


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _tables(cands, w, prior, use_prior, prior_weight, prior_tol, tol, k, k_all, i_idx, ref_pair, slot_pair, own, arrival, unary, table,
            free_best, root, tops, lane_tables, lane_own, e, filled):
    """One event's tables per reference r, as numpy builds its pair tables; slot s of reference r is mic s + (s ≥ r).

    ``arrival`` (R, S, k): candidate arrival times relative to the reference. ``table`` (R, P, k, k):
    the pair tables by the ranks of the pair's mics, −inf where an arrival time is missing; those of
    the pairs with the reference depend on the other mic's rank alone (the predicted lag is the
    candidate itself: ``own`` (P, k) holds them once per pair), so only the reference's rank 0 is
    filled, and ``unary`` (R, 1, S, k) holds them by slot too (shaped as ``joint`` of
    :func:`_children`, whose parent it is at the root). For the bounds
    (:func:`_branch_and_bound`): ``free_best`` (R, S + 1), the sum of the largest entries of the
    pairs of slots d … S − 1, and ``root`` (R,), the bound with every slot free. ``x − x == 0``
    tests that x is finite (a NaN or infinite x gives NaN).

    Where ``filled`` the own entries and the pair tables of the pairs without the reference come
    from the lanes (:func:`_lane_tables`: this event's are ``lane_own[..., e]``,
    ``lane_tables[..., e]`` and their largest entries ``tops[:, :, e]``; ``w`` is then not read);
    otherwise they are computed here (:func:`_entry`, :func:`_pair_table`) and the tables' largest
    entries stored in ``tops[:, :, e]``.
    """
    n_pairs = cands.shape[0]
    m, n_slots = arrival.shape[0], arrival.shape[1]
    for p in range(n_pairs):
        for q in range(k):
            if filled:
                own[p, q] = lane_own[p, q, e]
            else:
                x = cands[p, q]
                own[p, q] = _entry(x, cands, w, p, k_all, tol, use_prior, prior[p], prior_weight, prior_tol) if x - x == 0.0 else -np.inf
    for r in range(m):
        top_unary = 0.0
        for s in range(n_slots):
            p = ref_pair[r, s]
            first = i_idx[p] == r
            top = -np.inf
            for q in range(k):
                arrival[r, s, q] = _arrival(cands[p, q], first)
                unary[r, 0, s, q] = own[p, q]
                if first:
                    table[r, p, 0, q] = own[p, q]
                else:
                    table[r, p, q, 0] = own[p, q]
                top = max(top, own[p, q])
            top_unary += top
        free_best[r, n_slots] = 0.0
        for s in range(n_slots - 1, -1, -1):
            total = 0.0
            for s2 in range(s + 1, n_slots):
                p = slot_pair[r, s, s2]
                if filled:
                    for a in range(3):
                        for q in range(3):
                            table[r, p, a, q] = lane_tables[r, p, a, q, e]
                else:
                    tops[r, p, e] = _pair_table(cands, w, p, k_all, arrival, r, s, s2, k, tol, use_prior, prior[p], prior_weight, prior_tol,
                                                table)
                total += tops[r, p, e]
            free_best[r, s] = free_best[r, s + 1] + total
        root[r] = free_best[r, 0] + top_unary


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _leaf_score(arrival, table, r, ranks, mic_rank, i_idx, j_idx, lateness_weight, t, late):
    """The final score of hypothesis (reference r, slot ranks; ``mic_rank`` the same by mic, 0 for the reference) as the
    numpy search computes it: the raw score summed in pair order from 0, less the lateness penalty (:func:`_lateness`);
    its arrival times (by mic) land in t."""
    m = t.shape[0]
    raw = 0.0
    for p in range(i_idx.shape[0]):
        raw += table[r, p, mic_rank[i_idx[p]], mic_rank[j_idx[p]]]
    t[r] = 0.0
    for s in range(m - 1):
        t[s + (s >= r)] = arrival[r, s, ranks[s]]
    return _final(raw, _lateness(t, m, late), lateness_weight)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _deviation(t, ref_t, m):
    """Largest |(t_n − t_0) − (ref_n − ref_0)|, s (NaN where a time is NaN, as numpy's max)."""
    dev = abs(t[0] - t[0] - (ref_t[0] - ref_t[0]))
    for n in range(1, m):
        dev = _numpy_max(dev, abs(t[n] - t[0] - (ref_t[n] - ref_t[0])))
    return dev


#: What :func:`_branch_and_bound` looks for.
_COLLECT, _WINNER, _RUNNER_UP = 0, 1, 2


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _children(parent, pd, pq, parent_fixed, table, free_best, slot_pair, r, d, k, fixed, joint, bounds):
    """The children of a node whose slots < d are fixed (their entries summing to ``parent_fixed``; ``parent[pd, pq]``
    (S, k): each free slot's entries by rank with the reference and the fixed slots): for each rank q of slot d, its
    fixed entries ``fixed[d, q]``, its free slots' joint entries ``joint[d, q]`` and its bound ``bounds[d, q]``. With
    three ranks (the default) the ranks of each free slot are spelled out: the same sums, some 0.45 µs less per 6-mic
    event than the loop over k (which the compiler unrolls for four)."""
    n_slots = parent.shape[2]
    if k == 3:
        for q in range(3):
            score = parent_fixed + parent[pd, pq, d, q]
            bound = score + free_best[r, d + 1]
            for s in range(d + 1, n_slots):
                pair = slot_pair[r, d, s]
                x0 = parent[pd, pq, s, 0] + table[r, pair, q, 0]
                x1 = parent[pd, pq, s, 1] + table[r, pair, q, 1]
                x2 = parent[pd, pq, s, 2] + table[r, pair, q, 2]
                joint[d, q, s, 0] = x0
                joint[d, q, s, 1] = x1
                joint[d, q, s, 2] = x2
                bound += max(max(max(-np.inf, x0), x1), x2)
            fixed[d, q], bounds[d, q] = score, bound
        return
    for q in range(k):
        score = parent_fixed + parent[pd, pq, d, q]
        bound = score + free_best[r, d + 1]
        for s in range(d + 1, n_slots):  # later slots: their entries with slot d at rank q join the rest
            pair = slot_pair[r, d, s]
            top = -np.inf
            for q2 in range(k):
                x = parent[pd, pq, s, q2] + table[r, pair, q, q2]
                joint[d, q, s, q2] = x
                top = max(top, x)
            bound += top
        fixed[d, q], bounds[d, q] = score, bound


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _branch_and_bound(arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, lateness_weight, mode, level, far, tol,
                      win_t, ranks, mic_rank, fixed, joint, bounds, time_sum, time_min, t, late, kept_score, kept_times):
    """Branch and bound over every reference's slot ranks, depth first in index order (the numpy search's order).

    A node fixes the reference and slots 0 … d. Its bound on the raw score of every hypothesis
    below it is the sum of the entries of the pairs it fixes, plus for every free slot its best
    rank's entries with the reference and the fixed slots together (``joint``: per node, free
    slot and rank), plus the largest entry of every pair of free slots (``free_best``). Less the
    smallest lateness penalty its fixed mics already imply (the earliest of all mics is no later
    than the earliest fixed one, and free mics add ≥ 0), that bounds every final score below it.
    A node is skipped when its bound lies below ``level`` by more than rounding (10⁻¹² relative);
    leaves that are not are scored exactly (:func:`_leaf_score`).

    ``mode`` :data:`_COLLECT`: ``level`` is θ, a certified lower bound on the runner-up's score
    (:func:`_winner_one_pass`); every leaf scoring ≥ θ is kept in index order (score and
    arrival times), and θ rises to the lower score of any two kept leaves whose patterns lie more
    than ``far`` apart. Returns (number kept, θ, −1, −1); −1 kept when more than
    ``kept_score``'s length would be. :data:`_WINNER`: the first highest leaf above ``level``
    (−inf); :data:`_RUNNER_UP`: the highest of those more than ``tol`` from ``win_t``, above
    ``level`` (a score an eligible pattern reaches). Both return (0, best score, reference,
    slot code), (0, ``level``, −1, −1) when no leaf scores above it. ``ranks`` (S,): the slots' ranks, ``mic_rank`` (M,): the
    same by mic; ``time_sum``, ``time_min`` (S,), ``fixed``, ``bounds`` (S, k) and ``joint`` (S, k, S, k): scratch per
    depth (:func:`_children`).
    """
    m, n_slots = arrival.shape[0], arrival.shape[1]
    n_kept, best_r, best_code = 0, -1, -1
    floor = level - 1e-12 * (1.0 + abs(level))  # level less rounding: what a node's bound must reach
    for r in range(m):
        if root[r] == -np.inf or root[r] < floor:
            continue
        _children(unary, r, 0, 0.0, table, free_best, slot_pair, r, 0, k, fixed, joint, bounds)
        ranks[0], time_sum[0], time_min[0] = -1, 0.0, 0.0
        mic_rank[r] = 0
        d = 0  # the slot being fixed; slots < d are fixed at ranks[:d]
        while d >= 0:
            q = ranks[d] + 1
            if q == k:
                d -= 1
                continue
            ranks[d] = q
            v = arrival[r, d, q]
            t_sum, t_min = time_sum[d] + v, min(time_min[d], v)
            bound = bounds[d, q]
            if bound == -np.inf or bound - lateness_weight * max(t_sum - (d + 2) * t_min, 0.0) < floor:
                continue
            mic_rank[d + (d >= r)] = q
            if d + 1 < n_slots:
                _children(joint, d, q, fixed[d, q], table, free_best, slot_pair, r, d + 1, k, fixed, joint, bounds)
                d += 1
                ranks[d], time_sum[d], time_min[d] = -1, t_sum, t_min
                continue
            score = _leaf_score(arrival, table, r, ranks, mic_rank, i_idx, j_idx, lateness_weight, t, late)
            if mode == _COLLECT:
                if score > -np.inf and score >= floor:
                    if n_kept == kept_score.shape[0]:
                        return -1, level, -1, -1
                    for y in range(n_kept):  # only a pair whose lower score is above θ can raise it
                        low = min(score, kept_score[y])
                        if low > level and _deviation(t, kept_times[y], m) > far:
                            level = low
                    floor = level - 1e-12 * (1.0 + abs(level))
                    kept_score[n_kept] = score
                    kept_times[n_kept, :] = t
                    n_kept += 1
            elif score > level and (mode == _WINNER or _deviation(t, win_t, m) > tol):
                level, best_r, best_code = score, r, 0
                floor = level - 1e-12 * (1.0 + abs(level))
                for s in range(n_slots):
                    best_code = best_code * k + ranks[s]
    return n_kept, level, best_r, best_code


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _branch_and_bound_cold(arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, lateness_weight, mode, level, far, tol,
                           win_t, ranks, mic_rank, fixed, joint, bounds, time_sum, time_min, t, late, kept_score, kept_times):
    """:func:`_branch_and_bound` as a call, for the rare two-pass search (:func:`_winner`): one more compiled copy, not two."""
    return _branch_and_bound(arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, lateness_weight, mode, level, far, tol,
                             win_t, ranks, mic_rank, fixed, joint, bounds, time_sum, time_min, t, late, kept_score, kept_times)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _score_of_cold(arrival, table, r, ranks, mic_rank, i_idx, j_idx, lateness_weight, t, late):
    """:func:`_leaf_score` of reference r and slot ranks ``ranks`` (fills ``mic_rank``), as a call: it serves the rare
    paths only (each inlined copy costs compile time)."""
    mic_rank[r] = 0
    for s in range(ranks.shape[0]):
        mic_rank[s + (s >= r)] = ranks[s]
    return _leaf_score(arrival, table, r, ranks, mic_rank, i_idx, j_idx, lateness_weight, t, late)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _winner(arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, lateness_weight, tol, ranks, mic_rank, fixed, joint,
            bounds, time_sum, time_min, t, late, win_t, kept_score, kept_times):
    """The winner's arrival times into win_t and the score margin over the runner-up (NaN without one), in two passes."""
    m, n_slots = arrival.shape[0], arrival.shape[1]
    # pass 1: the winner, the first hypothesis in index order with the highest final score
    _, win_score, r, code = _branch_and_bound_cold(arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, lateness_weight,
                                              _WINNER, -np.inf, 0.0, tol, win_t, ranks, mic_rank, fixed, joint, bounds, time_sum,
                                              time_min, t, late, kept_score, kept_times)
    if r < 0:  # every hypothesis misses an arrival time: the first hypothesis (reference 0, ranks 0)
        ranks[:] = 0
        _score_of_cold(arrival, table, 0, ranks, mic_rank, i_idx, j_idx, lateness_weight, win_t, late)
        return np.nan
    for s in range(n_slots - 1, -1, -1):
        ranks[s] = code % k
        code //= k
    _score_of_cold(arrival, table, r, ranks, mic_rank, i_idx, j_idx, lateness_weight, win_t, late)
    # pass 2: the runner-up, the best final score of a pattern more than the tolerance from the winner's;
    # the winner's one-slot variants give it a score to prune from (often the runner-up's own)
    start = -np.inf
    for s in range(n_slots):
        own = ranks[s]
        for q in range(k):
            if q != own:
                ranks[s] = q
                score = _score_of_cold(arrival, table, r, ranks, mic_rank, i_idx, j_idx, lateness_weight, t, late)
                if score > start and _deviation(t, win_t, m) > tol:
                    start = score
        ranks[s] = own
    runner = _branch_and_bound_cold(arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, lateness_weight, _RUNNER_UP, start,
                               0.0, tol, win_t, ranks, mic_rank, fixed, joint, bounds, time_sum, time_min, t, late, kept_score,
                               kept_times)[1]
    return win_score - runner if np.isfinite(runner) else np.nan


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _winner_one_pass(arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, lateness_weight, tol, ranks, mic_rank, fixed,
                     joint, bounds, time_sum, time_min, t, late, base, win_t, kept_score, kept_times):
    """:func:`_winner` in one branch and bound (:data:`_COLLECT`) where the hypotheses it keeps fit the buffers, else in two.

    θ starts from reference 0's hypothesis of top-ranked lags and its one-slot variants: the lower
    score of it and any variant whose pattern lies more than twice the tolerance from it (by the
    triangle inequality one of the two lies more than the tolerance from the winner's pattern,
    whichever it is). The first hypothesis' raw score is summed slot by slot and a variant's is the
    first's plus the change in the moved mic's pairs, both in another order than the numpy
    search's: they may differ from the exact scores by rounding (~10⁻¹⁶ relative), which the
    search's floor (10⁻¹² relative below θ) absorbs; θ only prunes, every kept score is exact. Where the first hypothesis misses an arrival time (or its
    score overflows) θ stays −inf: no variant's pattern is then more than the tolerance from another
    (numpy's deviation is NaN).
    """
    m, n_slots = arrival.shape[0], arrival.shape[1]
    far = 2 * tol * (1 + 1e-9) + 1e-15  # a hair over twice the tolerance, for rounding
    theta = -np.inf
    raw = 0.0  # the first hypothesis' raw score, in any order (θ need not be exact: the search's floor allows for rounding)
    base[0] = 0.0  # its arrival times: reference 0's, each slot at rank 0
    for s in range(n_slots):
        base[s + 1] = arrival[0, s, 0]
        raw += unary[0, 0, s, 0]
        for s2 in range(s + 1, n_slots):
            raw += table[0, slot_pair[0, s, s2], 0, 0]
    finite = raw - raw == 0.0
    for n in range(m):
        finite &= base[n] - base[n] == 0.0
    first = _final(raw, _lateness(base, m, late), lateness_weight)
    if finite:  # each one-slot variant's score from the first's, by the entries of the moved mic's pairs
        t[:] = base
        for s in range(n_slots):
            for q in range(1, k):
                v = arrival[0, s, q]
                if not abs(v - base[s + 1]) > far:
                    continue
                change = unary[0, 0, s, q] - unary[0, 0, s, 0]
                for s2 in range(n_slots):
                    if s2 < s:
                        pair = slot_pair[0, s2, s]
                        change += table[0, pair, 0, q] - table[0, pair, 0, 0]
                    elif s2 > s:
                        pair = slot_pair[0, s, s2]
                        change += table[0, pair, q, 0] - table[0, pair, 0, 0]
                t[s + 1] = v
                score = _final(raw + change, _lateness(t, m, late), lateness_weight)
                t[s + 1] = base[s + 1]
                if score - score == 0.0:
                    theta = max(theta, min(first, score))
    n_kept = _branch_and_bound(arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, lateness_weight, _COLLECT, theta, far,
                               tol, win_t, ranks, mic_rank, fixed, joint, bounds, time_sum, time_min, t, late, kept_score, kept_times)[0]
    if n_kept < 0:  # more candidates than the buffers hold (many near-ties): two passes
        return _winner(arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, lateness_weight, tol, ranks, mic_rank, fixed,
                       joint, bounds, time_sum, time_min, t, late, win_t, kept_score, kept_times)
    win = -1
    for h in range(n_kept):  # the first highest, in index order
        if win < 0 or kept_score[h] > kept_score[win]:
            win = h
    if win < 0:  # every hypothesis misses an arrival time: the first hypothesis (reference 0, ranks 0)
        ranks[:] = 0
        _score_of_cold(arrival, table, 0, ranks, mic_rank, i_idx, j_idx, lateness_weight, win_t, late)
        return np.nan
    win_t[:] = kept_times[win]
    runner = -np.inf
    for h in range(n_kept):
        if kept_score[h] > runner and _deviation(kept_times[h], win_t, m) > tol:
            runner = kept_score[h]
    return kept_score[win] - runner if np.isfinite(runner) else np.nan


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
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


#: Events whose pair tables :func:`_lane_tables` computes together, one per vector lane: 32 was the fastest of 8, 16, 32
#: and 64 on the solver_speed detections (8 ran 20 % slower than one event at a time).
LANES = 32
#: The most memory the lanes' pair tables may take (arrays of up to 14 mics); larger arrays fill them event by event.
_LANE_BYTES = 8 * 2**20


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _gather_lanes(cands, weights, prior, use_prior, b0, nb, i_idx, ref_pair, lane_arrival, lane_cands, lane_w, lane_prior):
    """Events b0 … b0 + nb − 1 into lanes 0 … nb − 1 (the spare lanes of a last, partial block are left alone and never read):
    candidates, cleaned weights and prior lags by (pair, rank, lane), arrival times by (reference, slot, rank, lane), as
    :func:`_tables` forms them for one event."""
    n_pairs, k_all = cands.shape[1], cands.shape[2]
    m, n_slots = lane_arrival.shape[0], lane_arrival.shape[1]
    for e in range(nb):
        b = b0 + e
        for p in range(n_pairs):
            lane_prior[p, e] = prior[b, p] if use_prior else 0.0
            for rr in range(k_all):
                x = cands[b, p, rr]
                lane_cands[p, rr, e] = x
                lane_w[p, rr, e] = _clean_weight(weights[b, p, rr], x)
        for r in range(m):
            for s in range(n_slots):
                p = ref_pair[r, s]
                first = i_idx[p] == r
                for q in range(3):
                    lane_arrival[r, s, q, e] = _arrival(cands[b, p, q], first)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _lane_tables(nb, lane_arrival, lane_cands, lane_w, lane_prior, use_prior, prior_weight, prior_tol, tol, slot_pair, tables, tops, lane_own):
    """The tables of three candidates (k = K = 3) of the events in lanes 0 … nb − 1, the lanes innermost so that the compiler
    vectorizes them, each entry by :func:`_entry_of_three` (the formula of :func:`_entry` and :func:`_pair_table`, so the
    same values bit for bit): each candidate's own entry (its pair's entry for the candidate itself as the predicted lag,
    −inf for a missing one) in ``lane_own[p, q, e]``, and for the pairs without the reference, entry (a, c) of pair p under
    reference r in ``tables[r, p, a, c, e]`` (−inf where an arrival time is missing) and the table's largest entry in
    ``tops[r, p, e]``. :func:`_tables` fills the pairs with the reference per event from the own entries."""
    m, n_slots = lane_arrival.shape[0], lane_arrival.shape[1]
    for p in range(lane_cands.shape[0]):
        for q in range(3):
            for e in range(nb):
                x = lane_cands[p, q, e]
                val = _entry_of_three(x, lane_cands[p, 0, e], lane_cands[p, 1, e], lane_cands[p, 2, e], lane_w[p, 0, e], lane_w[p, 1, e],
                                      lane_w[p, 2, e], tol, use_prior, lane_prior[p, e], prior_weight, prior_tol)
                lane_own[p, q, e] = val if x - x == 0.0 else -np.inf
    for r in range(m):
        for s in range(n_slots):
            for s2 in range(s + 1, n_slots):
                p = slot_pair[r, s, s2]
                for e in range(nb):
                    tops[r, p, e] = -np.inf
                for a in range(3):
                    for c in range(3):
                        for e in range(nb):
                            ai = lane_arrival[r, s, a, e]
                            aj = lane_arrival[r, s2, c, e]
                            val = _entry_of_three(aj - ai, lane_cands[p, 0, e], lane_cands[p, 1, e], lane_cands[p, 2, e], lane_w[p, 0, e],
                                                  lane_w[p, 1, e], lane_w[p, 2, e], tol, use_prior, lane_prior[p, e], prior_weight, prior_tol)
                            val = val if (ai - ai == 0.0 and aj - aj == 0.0) else -np.inf
                            tables[r, p, a, c, e] = val
                            tops[r, p, e] = max(tops[r, p, e], val)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _select(cands, weights, prior, use_prior, prior_weight, prior_tol, tol, k, k_all, i_idx, j_idx, ref_pair, slot_pair, lateness_weight,
            times_out, trusted_out, diag_out):
    """Every event's selection into ``times_out``, ``trusted_out`` and ``diag_out`` (:func:`select_compiled`), the helpers
    inlined and each event's rows copied in and out by index (module docstring)."""
    bsz, n_pairs = cands.shape[0], cands.shape[1]
    m = times_out.shape[1]
    n_slots = m - 1
    c = np.empty((n_pairs, k_all))
    w = np.empty((n_pairs, k_all))
    event_prior = np.empty(n_pairs)
    own = np.empty((n_pairs, k))
    arrival, unary = np.empty((m, n_slots, k)), np.empty((m, 1, n_slots, k))
    n_lanes = LANES
    filled = k == 3 and k_all == 3 and m * n_pairs * 9 * n_lanes * 8 <= _LANE_BYTES  # pair tables from the lanes
    if not filled:
        n_lanes = 1  # each event's pair tables in turn (_pair_table)
    tables, tops = np.empty((m, n_pairs, k, k, n_lanes)), np.empty((m, n_pairs, n_lanes))
    table = np.empty((m, n_pairs, k, k))
    lane_arrival, lane_cands = np.empty((m, n_slots, 3, n_lanes)), np.empty((n_pairs, k_all, n_lanes))
    lane_w, lane_prior = np.empty((n_pairs, k_all, n_lanes)), np.empty((n_pairs, n_lanes))
    lane_own = np.empty((n_pairs, k_all, n_lanes))
    free_best, root = np.empty((m, n_slots + 1)), np.empty(m)
    ranks, mic_rank = np.zeros(n_slots, np.int64), np.zeros(m, np.int64)
    fixed, joint, bounds = np.empty((n_slots, k)), np.empty((n_slots, k, n_slots, k)), np.empty((n_slots, k))
    time_sum, time_min, t, late, base = np.empty(n_slots), np.empty(n_slots), np.empty(m), np.empty(m), np.empty(m)
    kept_score, kept_times = np.empty(_KEPT), np.empty((_KEPT, m))
    win_t = np.empty(m)
    gap_ok = np.empty(n_pairs, np.bool_)
    chosen = np.empty(n_pairs)
    per_mic, rhs = np.empty(m), np.empty(m)
    normal = np.empty((m, m))
    times, trusted, diag = np.empty(m), np.empty(m, np.bool_), np.empty(diag_out.shape[1])
    for b0 in range(0, bsz, n_lanes):
        nb = min(n_lanes, bsz - b0)
        if filled:
            _gather_lanes(cands, weights, prior, use_prior, b0, nb, i_idx, ref_pair, lane_arrival, lane_cands, lane_w, lane_prior)
            _lane_tables(nb, lane_arrival, lane_cands, lane_w, lane_prior, use_prior, prior_weight, prior_tol, tol, slot_pair, tables, tops,
                         lane_own)
        for e in range(nb):
            b = b0 + e
            for p in range(n_pairs):
                event_prior[p] = prior[b, p]
                for rr in range(k_all):
                    c[p, rr] = cands[b, p, rr]
                    if not filled:
                        w[p, rr] = _clean_weight(weights[b, p, rr], c[p, rr])
            _tables(c, w, event_prior, use_prior, prior_weight, prior_tol, tol, k, k_all, i_idx, ref_pair, slot_pair, own, arrival, unary, table,
                    free_best, root, tops, tables, lane_own, e, filled)
            diag[2] = _winner_one_pass(arrival, unary, table, free_best, root, k, i_idx, j_idx, slot_pair, lateness_weight, tol, ranks, mic_rank,
                                       fixed, joint, bounds, time_sum, time_min, t, late, base, win_t, kept_score, kept_times)
            _trust_and_fit(c, tol, win_t, i_idx, j_idx, gap_ok, chosen, per_mic, normal, rhs, times, trusted, diag)
            for n in range(m):
                times_out[b, n], trusted_out[b, n] = times[n], trusted[n]
            for n in range(diag.shape[0]):
                diag_out[b, n] = diag[n]
