"""The best consistent-set hypothesis and its runner-up: exhaustive search and exact branch and bound.

A hypothesis picks a reference mic r and, for every other mic n, one of the K candidate lags of
the pair (r, n); that fixes every mic's arrival time relative to r (M · K^(M−1) hypotheses,
numbered r · K^(M−1) + Σ_s rank(slot s) · K^(M−2−s), where the slots are the mics other than r in
increasing order). Its *raw* score is a sum over the P pairs of a table entry that depends only on
the ranks of the pair's two mics (``table[b, r, p, rank_i, rank_j]``, −inf where an arrival time
is missing); its *final* score is raw − 10⁻³ × lateness (the summed delay of every mic behind the
earliest). The winner is the first hypothesis in index order with the highest final score (the
first hypothesis where every score is −inf); the runner-up is the best final score among
hypotheses whose arrival pattern differs from the winner's by more than the tolerance.

``exhaustive_best`` scores every hypothesis; its cost and memory grow as K^(M−1).
``pruned_best`` gives the same answer, bit for bit, while scoring a few dozen per event:

1. **Seeds.** The hypotheses with at most one candidate other than each pair's best are scored.
   Their winner h₁ (final f₁) and the best seed h₂ (final f₂) whose pattern differs from h₁'s by
   more than twice the tolerance give a threshold θ = f₂. The true winner scores ≥ f₁ ≥ θ, and so
   does the true runner-up: if the winner's pattern is within the tolerance of h₁'s, it differs
   from h₂'s by more than the tolerance (triangle inequality), so h₂ is eligible; otherwise h₁ is.
   Without such a pair, θ = −inf (every finite hypothesis is kept).
2. **Branch and bound.** Per event and reference mic, the other mics are assigned one at a time.
   A partial assignment's bound is its exact partial score, plus for every pair with one mic
   assigned the best entry given that mic's rank, plus for every pair with neither assigned the
   pair's best entry. Final ≤ raw ≤ bound, so a branch whose bound is below θ (or −inf) holds
   neither the winner nor the runner-up and is cut.
3. **Exact scores.** The surviving hypotheses are scored as the exhaustive search scores them
   (sums in pair order, the same lateness), in index order, so ties break the same way.

Written by hand: no library does a vectorised branch and bound over a dense pairwise score.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np
from scipy import sparse

#: Penalty per second of lateness in the final score (a reflection only ever delays a mic).
LATENESS_WEIGHT = 1e-3


def pairs_of(n_mics: int) -> list[tuple[int, int]]:
    """Mic pairs (i, j), i < j, in the project's pair order."""
    return [(i, j) for i in range(n_mics) for j in range(i + 1, n_mics)]


@dataclass(frozen=True)
class PairLayout:
    """Index arrays of the pairs of M mics, and the slots (other mics in increasing order) of every reference mic."""

    n_mics: int
    i_idx: np.ndarray  # (P,) first mic of each pair (i < j)
    j_idx: np.ndarray  # (P,) second mic of each pair
    pair_index: np.ndarray  # (M, M) pair index of {a, b} (0 on the diagonal, never used)
    ref_pair: np.ndarray  # (R, M) pair index of (r, n) (−1 for n = r)
    ref_sign: np.ndarray  # (R, M) +1 where t_n − t_r = τ_pair, −1 where it is −τ_pair, 0 for n = r
    mic_of_slot: np.ndarray  # (R, M−1) slot s of reference r is mic s + (s >= r)


@functools.lru_cache(maxsize=32)
def pair_layout(n_mics: int) -> PairLayout:
    """``PairLayout`` of ``n_mics`` mics (cached)."""
    pairs = pairs_of(n_mics)
    pair_index = np.zeros((n_mics, n_mics), dtype=np.intp)
    for n, (i, j) in enumerate(pairs):
        pair_index[i, j] = pair_index[j, i] = n
    other = ~np.eye(n_mics, dtype=bool)
    ref_pair = np.where(other, pair_index, -1)
    ref_sign = np.where(other, np.where(np.arange(n_mics)[:, None] < np.arange(n_mics)[None, :], 1.0, -1.0), 0.0)
    slots = np.arange(n_mics - 1)
    mic_of_slot = slots[None, :] + (slots[None, :] >= np.arange(n_mics)[:, None])
    return PairLayout(
        n_mics,
        np.array([p[0] for p in pairs], dtype=np.intp),
        np.array([p[1] for p in pairs], dtype=np.intp),
        pair_index,
        ref_pair,
        ref_sign,
        mic_of_slot,
    )


@dataclass(frozen=True)
class HypothesisDesign:
    """Every hypothesis of M mics and K candidates per pair, as index arrays (for the exhaustive search)."""

    layout: PairLayout
    k: int
    time_index: np.ndarray  # (H, M) flat index into the (R, M, K) arrival times
    table_sum: sparse.csr_matrix  # (R·P·K·K, H): column h sums the P pair-table entries of hypothesis h


@functools.lru_cache(maxsize=16)
def hypothesis_design(n_mics: int, k: int) -> HypothesisDesign:
    """``HypothesisDesign`` for ``n_mics`` mics and ``k`` candidates per pair (cached)."""
    layout = pair_layout(n_mics)
    i_idx, j_idx = layout.i_idx, layout.j_idx
    time_rows, table_rows = [], []
    n_pairs = len(i_idx)
    for ref in range(n_mics):
        for combo in itertools.product(range(k), repeat=n_mics - 1):
            rank = np.zeros(n_mics, dtype=int)
            rank[layout.mic_of_slot[ref]] = combo
            time_rows.append((ref * n_mics + np.arange(n_mics)) * k + rank)
            table_rows.append(((ref * n_pairs + np.arange(n_pairs)) * k + rank[i_idx]) * k + rank[j_idx])
    table_index = np.array(table_rows)
    n_hyp = len(table_index)
    table_sum = sparse.csr_matrix(
        (np.ones(table_index.size), (table_index.ravel(), np.repeat(np.arange(n_hyp), n_pairs))), shape=(n_mics * n_pairs * k * k, n_hyp)
    )
    return HypothesisDesign(layout, k, np.array(time_rows), table_sum)


def _final_scores(raw: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Final scores from raw scores (...,) and arrival times (..., M) (both searches use this, for identical rounding)."""
    lateness = (times - times.min(axis=-1, keepdims=True)).sum(axis=-1)
    return raw - LATENESS_WEIGHT * np.nan_to_num(lateness, nan=1e3)


def _margin(best_score: np.ndarray, runner_up: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):  # −inf − −inf where every hypothesis misses an arrival: NaN either way
        return np.where(np.isfinite(runner_up), best_score - runner_up, np.nan)


def _deviation(times: np.ndarray, relative: np.ndarray) -> np.ndarray:
    """Largest difference, s, of arrival patterns (..., M) from reference patterns relative to mic 0 (broadcast)."""
    return np.abs(times - times[..., :1] - relative).max(-1)


def _score(
    raw: np.ndarray, flat_arrival: np.ndarray, design: HypothesisDesign, hyp: np.ndarray, tolerance_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Final scores of the hypotheses ``hyp`` (B, L), index order: the winner's times (B, M), its score and the runner-up's."""
    rows = np.arange(raw.shape[0])
    times = flat_arrival[rows[:, None, None], design.time_index[hyp]]  # (B, L, M)
    score = _final_scores(np.take_along_axis(raw, hyp, axis=1), times)
    best = np.argmax(score, axis=1)
    best_times = times[rows, best]
    relative = (best_times - best_times[:, :1])[:, None, :]
    runner_up = np.where(_deviation(times, relative) > tolerance_s, score, -np.inf).max(axis=1)
    return best_times, score[rows, best], runner_up


def exhaustive_best(table: np.ndarray, arrival: np.ndarray, design: HypothesisDesign, tolerance_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The winner's arrival times (B, M) and the score margin (B,) over the runner-up, every hypothesis scored.

    ``table`` (B, R, P, K, K) pair-table entries (−inf where an arrival is missing); ``arrival``
    (B, R, M, K) candidate arrival times. The penalty is bounded, so only the highest raw scores can
    win: they are scored in full, and a row whose winner or runner-up could lie outside them is
    scored over every hypothesis (same result, exactly).
    """
    bsz = table.shape[0]
    flat_arrival = arrival.reshape(bsz, -1)
    raw = table.reshape(bsz, -1) @ design.table_sum  # (B, H): the sum over pairs, in pair order
    n_hyp = raw.shape[1]
    n_top = min(n_hyp, 8 * design.layout.n_mics)
    if n_top < n_hyp:
        top = np.sort(np.argpartition(-raw, n_top - 1, axis=1)[:, :n_top], axis=1)  # index order: ties as argmax
    else:
        top = np.broadcast_to(np.arange(n_hyp), (bsz, n_hyp))
    best_times, best_score, runner_up = _score(raw, flat_arrival, design, top, tolerance_s)
    if n_top < n_hyp:
        outside = np.take_along_axis(raw, top, axis=1).min(axis=1)  # no hypothesis outside scores above this
        unsure = np.isfinite(outside) & ~((best_score > outside) & (runner_up > outside))
        if unsure.any():
            every = np.broadcast_to(np.arange(n_hyp), (int(unsure.sum()), n_hyp))
            best_times[unsure], best_score[unsure], runner_up[unsure] = _score(
                raw[unsure], flat_arrival[unsure], design, every, tolerance_s
            )
    dead = ~np.isfinite(raw).any(axis=1)  # every hypothesis misses an arrival: the first one
    best_times[dead] = flat_arrival[dead][:, design.time_index[0]]
    return best_times, _margin(best_score, runner_up)


def _chain(op: np.ufunc, parts: np.ndarray) -> np.ndarray:
    """op(…op(op(parts[0], parts[1]), parts[2])…) over the first axis: numpy's reductions over a 2–6 long axis are ~10× slower."""
    out = parts[0]
    for part in parts[1:]:
        out = op(out, part)
    return out


def _seeds(layout: PairLayout, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Reference (S,) and ranks by mic (S, M) of the hypotheses with at most one rank other than 0."""
    refs, ranks = [], []
    m = layout.n_mics
    for ref in range(m):
        refs.append(ref)
        ranks.append(np.zeros(m, dtype=np.intp))
        for mic in layout.mic_of_slot[ref]:
            for rank in range(1, k):
                refs.append(ref)
                ranks.append(np.eye(m, dtype=np.intp)[mic] * rank)
    return np.array(refs), np.array(ranks)


@functools.lru_cache(maxsize=32)
def _seed_offsets(n_mics: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Table (S, P) and arrival (S, M) offsets of the seed hypotheses of ``n_mics`` mics and ``k`` candidates (cached, read-only)."""
    layout = pair_layout(n_mics)
    ref, ranks = _seeds(layout, k)
    offsets = _table_offsets(layout, k, ref, ranks), _arrival_offsets(layout, k, ref, ranks)
    for array in offsets:
        array.setflags(write=False)
    return offsets


def _table_offsets(layout: PairLayout, k: int, ref: np.ndarray, ranks: np.ndarray) -> np.ndarray:
    """Flat offsets (N, P) into one event's (R, P, K, K) table of hypotheses given by reference (N,) and ranks by mic (N, M)."""
    n_pairs = len(layout.i_idx)
    return ((ref[:, None] * n_pairs + np.arange(n_pairs)) * k + ranks[:, layout.i_idx]) * k + ranks[:, layout.j_idx]


def _arrival_offsets(layout: PairLayout, k: int, ref: np.ndarray, ranks: np.ndarray) -> np.ndarray:
    """Flat offsets (N, M) into one event's (R, M, K) arrival times."""
    return (ref[:, None] * layout.n_mics + np.arange(layout.n_mics)) * k + ranks


def _seed_threshold(table_flat: np.ndarray, flat_arrival: np.ndarray, layout: PairLayout, k: int, tolerance_s: float) -> np.ndarray:
    """θ per event (module docstring, step 1); −inf where the seeds give none.

    Computed with element-wise chains rather than numpy's reductions (faster over the short axes);
    their rounding differs from the exact scores by ~10⁻¹⁵, which the search's slack covers.
    """
    bsz = table_flat.shape[0]
    table_offsets, arrival_offsets = _seed_offsets(layout.n_mics, k)
    raw = _chain(np.add, np.moveaxis(table_flat[:, table_offsets], -1, 0))  # (B, S)
    times = flat_arrival[:, arrival_offsets]  # (B, S, M)
    mic_times = np.moveaxis(times, -1, 0)
    score = raw - LATENESS_WEIGHT * np.nan_to_num(_chain(np.add, mic_times - _chain(np.minimum, mic_times)), nan=1e3)
    rows = np.arange(bsz)
    best = np.argmax(score, axis=1)
    best_times = times[rows, best]
    relative = mic_times - mic_times[0] - np.moveaxis(best_times - best_times[:, :1], -1, 0)[:, :, None]
    far = _chain(np.maximum, np.abs(relative)) > 2 * tolerance_s * (1 + 1e-9) + 1e-15  # a hair over 2·tol for rounding
    theta = np.where(far & np.isfinite(score), score, -np.inf).max(axis=1)
    return np.where(np.isfinite(score[rows, best]), theta, -np.inf)


def _bound_terms(table: np.ndarray, layout: PairLayout) -> tuple[np.ndarray, np.ndarray]:
    """Bound terms per level t (t slots assigned): for mic a at rank q, Σ over unassigned mics b of the best
    entry of pair (a, b) given that rank, (B, R, T, M, K); and Σ over pairs of unassigned mics of their best entry, (B, R, T)."""
    bsz, n_ref = table.shape[:2]
    m = layout.n_mics
    ref = np.arange(n_ref)[:, None, None]
    slot_mic = np.broadcast_to(layout.mic_of_slot[:, None, :], (n_ref, m, m - 1))  # (R, a, s)
    mic = np.broadcast_to(np.arange(m)[None, :, None], (n_ref, m, m - 1))
    given_first, given_second = _chain(np.maximum, np.moveaxis(table, -1, 0)), _chain(np.maximum, np.moveaxis(table, -2, 0))
    best_given = np.stack([given_first, given_second], axis=2)  # (B, R, 2, P, K): given the pair's 1st / 2nd mic's rank
    per_slot = best_given[:, ref, (mic > slot_mic).astype(np.intp), layout.pair_index[mic, slot_mic]]  # (B, R, a, s, K)
    per_slot = np.where((mic == slot_mic)[None, :, :, :, None], 0.0, per_slot)
    edges = np.zeros((bsz, n_ref, m, m, table.shape[-1]))  # (B, R, T, a, K); level M−1: nothing open
    for t in range(m - 2, -1, -1):
        edges[:, :, t] = edges[:, :, t + 1] + per_slot[:, :, :, t]
    best_pair = _chain(np.maximum, np.moveaxis(given_first, -1, 0))  # (B, R, P)
    s1, s2 = np.triu_indices(m - 1, 1)
    pair_terms = best_pair[
        :, ref[:, :, 0], layout.pair_index[layout.mic_of_slot[:, s1], layout.mic_of_slot[:, s2]]
    ]  # (B, R, pairs of slots)
    pairs_open = np.zeros((bsz, n_ref, m))
    for t in range(m - 2, -1, -1):
        pairs_open[:, :, t] = pairs_open[:, :, t + 1] + _sum_columns(pair_terms, s1 == t)
    return edges, pairs_open


def _sum_columns(values: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """Σ of the selected last-axis columns of ``values`` (0 when none)."""
    return _chain(np.add, np.moveaxis(values[..., columns], -1, 0)) if columns.any() else np.zeros(values.shape[:-1])


def _enumerate(
    table: np.ndarray, theta: np.ndarray, layout: PairLayout, edges: np.ndarray, pairs_open: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Event (N,), reference (N,) and ranks by slot (N, M−1) of every hypothesis whose bound is ≥ θ and finite (step 2).

    Nodes are (event, reference, ranks of the slots assigned so far); every lookup is a gather from
    a flattened array at a computed offset (numpy's multi-array indexing costs several times more).
    """
    bsz, n_ref, n_pairs, k = table.shape[:4]
    m = layout.n_mics
    n_slots = m - 1
    edges, pairs_open = edges.reshape(-1), pairs_open.reshape(-1)  # from _bound_terms
    oriented = np.stack([table, np.swapaxes(table, -1, -2)], axis=2).reshape(-1)  # (B, R, 2, P, K, K): assigned mic's rank first
    per_node = 2 * n_pairs * k * k
    assigned_mic = np.concatenate([layout.mic_of_slot, np.arange(n_ref)[:, None]], axis=1)  # slot n_slots: the reference (rank 0)
    slack = 1e-9 * (1.0 + np.abs(np.where(np.isfinite(theta), theta, 0.0)))
    floor = theta - slack
    fan = np.arange(k)

    base = np.arange(bsz * n_ref)  # event · R + reference
    ref = base % n_ref
    first = edges[base * m * m * k + ref * k] + pairs_open[base * m]
    keep = (first >= floor[base // n_ref]) & (first > -np.inf)
    base, ref = base[keep], ref[keep]
    ranks = np.zeros((len(base), n_slots + 1), dtype=np.intp)  # by slot, then the reference's
    partial = np.zeros(len(base))
    for t in range(n_slots):
        mic = layout.mic_of_slot[ref, t]
        level = (base * m + t + 1) * m * k
        gain = np.zeros((len(base), k))
        bound = edges[(level + mic * k)[:, None] + fan] + pairs_open[base * m + t + 1][:, None]
        for slot in (n_slots, *range(t)):
            a = assigned_mic[ref, slot]
            offset = ((a > mic) * n_pairs + layout.pair_index[a, mic]) * k * k
            gain = gain + oriented[(base * per_node + offset + ranks[:, slot] * k)[:, None] + fan]
            bound = bound + edges[level + a * k + ranks[:, slot]][:, None]
        child = partial[:, None] + gain
        total = child + bound
        parent, rank = np.nonzero((total >= floor[base // n_ref][:, None]) & (total > -np.inf))
        base, ref, partial = base[parent], ref[parent], child[parent, rank]
        ranks = ranks[parent]
        ranks[:, t] = rank
    return base // n_ref, ref, ranks[:, :n_slots]


def _best_of(
    table_flat: np.ndarray,
    flat_arrival: np.ndarray,
    layout: PairLayout,
    k: int,
    ev: np.ndarray,
    ref: np.ndarray,
    slot_ranks: np.ndarray,
    tolerance_s: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact scores of enumerated hypotheses (step 3): per event found, its winner's times, score and the runner-up's."""
    m = layout.n_mics
    order = np.lexsort((ref * k ** (m - 1) + slot_ranks @ (k ** np.arange(m - 2, -1, -1)), ev))  # event, then hypothesis index
    ev, ref, slot_ranks = ev[order], ref[order], slot_ranks[order]
    ranks = np.zeros((len(ev), m), dtype=np.intp)
    ranks[np.arange(len(ev))[:, None], layout.mic_of_slot[ref]] = slot_ranks
    # raw summed in pair order from 0 (as the exhaustive search's sparse product), then the same final score
    entries = _table_offsets(layout, k, ref, ranks)
    raw = np.zeros(len(ev))
    for p in range(entries.shape[1]):
        raw = raw + table_flat[ev, entries[:, p]]
    times = flat_arrival[ev[:, None], _arrival_offsets(layout, k, ref, ranks)]  # (N, M)
    score = _final_scores(raw, times)
    if not len(ev):
        return ev, np.empty((0, m)), np.empty(0), np.empty(0)
    starts = np.flatnonzero(np.r_[True, ev[1:] != ev[:-1]])
    group = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(ev)]))
    top = np.maximum.reduceat(score, starts)
    first = np.minimum.reduceat(np.where(score == top[group], np.arange(len(ev)), len(ev)), starts)
    winner = times[first]
    runner_up = np.maximum.reduceat(np.where(_deviation(times, (winner - winner[:, :1])[group]) > tolerance_s, score, -np.inf), starts)
    return ev[starts], winner, score[first], runner_up


def pruned_best(table: np.ndarray, arrival: np.ndarray, layout: PairLayout, tolerance_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Same result as ``exhaustive_best``, bit for bit, by branch and bound (module docstring).

    The threshold is lowered step by step from the root's bound (θ = U − δ, δ = 1, 4, 16, … × the
    largest table entry) until the winner and the runner-up both score ≥ θ — then nothing below θ
    can matter — and never below the seeds' certified θ, where success is guaranteed.
    """
    bsz, n_ref, n_pairs, k = table.shape[:4]
    m = layout.n_mics
    table_flat = table.reshape(bsz, -1)
    flat_arrival = arrival.reshape(bsz, -1)
    certified = _seed_threshold(table_flat, flat_arrival, layout, k, tolerance_s)
    finite = np.where(np.isfinite(table_flat), table_flat, 0.0)
    step = np.maximum(np.abs(finite).max(axis=1), 1e-12)
    edges, pairs_open = _bound_terms(table, layout)
    root = (edges[:, :, 0, :, 0][:, np.arange(n_ref), np.arange(n_ref)] + pairs_open[:, :, 0]).max(axis=1)  # bound of every hypothesis
    span = np.abs(root) + n_pairs * step  # below root − span every finite hypothesis is included
    # winner of every event: the first hypothesis when every hypothesis misses an arrival
    best_times = flat_arrival[:, _arrival_offsets(layout, k, np.zeros(1, dtype=np.intp), np.zeros((1, m), dtype=np.intp))[0]].copy()
    margin = np.full(bsz, np.nan)
    pending = np.flatnonzero(np.isfinite(root))
    delta = step.copy()
    while len(pending):
        guess = root[pending] - delta[pending]
        theta = np.maximum(guess, certified[pending])
        final = (guess <= certified[pending]) | (delta[pending] > span[pending])  # certified, or below every finite hypothesis
        ev, ref, slot_ranks = _enumerate(table[pending], theta, layout, edges[pending], pairs_open[pending])
        found, winner, win_score, runner_up = _best_of(
            table_flat[pending], flat_arrival[pending], layout, k, ev, ref, slot_ranks, tolerance_s
        )
        done = np.zeros(len(pending), dtype=bool)
        done[found] = (win_score >= theta[found]) & (runner_up >= theta[found])
        done |= final
        accepted = np.isin(found, np.flatnonzero(done))
        best_times[pending[found[accepted]]] = winner[accepted]
        margin[pending[found[accepted]]] = _margin(win_score[accepted], runner_up[accepted])
        pending = pending[~done]
        delta[pending] *= 4
    return best_times, margin
