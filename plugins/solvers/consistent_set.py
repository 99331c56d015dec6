"""Consistent-set TDOA solver: the jointly consistent GCC candidates over *all* mic pairs, and the mics to trust.

A reflection, a trunk-scattered path or a noise burst can outrank the direct path in one pair's
GCC. Choosing among the candidates of the pairs with one reference mic cannot fix that when the
reference mic itself is the corrupted one. This solver therefore looks at every pair:

1. **Hypotheses.** For every reference mic r and every choice of one of the K candidate lags of
   each pair (r, m), the arrival times t_m − t_r follow. That is M · K^(M−1) hypotheses per event
   (forest, 6 mics, K = 3: 1,458), evaluated together as arrays for a chunk of events.
2. **Consistency (closure).** A pair (i, j) is consistent with a hypothesis when one of its own
   candidates lies within ``tolerance_s`` of t_j − t_i (τ_ij + τ_jk ≈ τ_ik). The score is the total
   GCC height of the consistent pairs; ties go to the earliest arrivals (the direct path arrives
   first). The best hypothesis wins; the runner-up's score is kept as a margin.
3. **Mics to trust.** A mic is trusted when it is consistent with at least two other mics; a mic
   whose direct path is blocked or buried in noise is left out, not averaged in (at least three
   mics are always kept).
4. **Refinement.** The arrival times of the trusted mics are the least-squares fit to the chosen
   lags of all their consistent pairs (averaging the redundant measurements), and the position is
   solved in closed form on the trusted mics with Levenberg–Marquardt polish
   (:class:`plugins.solvers.hyperbolic.HyperbolicSolver`).

Diagnostics per event: ``consistent_pairs``, ``consistency`` (share of the pairs among trusted
mics that are consistent), ``score_margin`` (best minus runner-up score, in GCC-height units),
``n_mics_used`` and ``closure_rms_s`` (RMS misfit of the chosen lags to the fitted arrival times).
They are the cues a gate and an error model can use.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np

from acoustlab.core.contracts import SolverInputs, SolverResult
from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.tdoa import solver_inputs
from plugins.solvers.hyperbolic import HyperbolicSolver

#: Diagnostics this solver adds to the hyperbolic solver's (catalogued in :data:`acoustlab.core.columns.SOLVER_CATALOG`).
EXTRA_DIAGNOSTICS = ("consistent_pairs", "consistency", "score_margin", "n_mics_used", "closure_rms_s")


def _pairs(n_mics: int) -> list[tuple[int, int]]:
    return [(i, j) for i in range(n_mics) for j in range(i + 1, n_mics)]


@functools.lru_cache(maxsize=16)
def _hypothesis_design(n_mics: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every hypothesis: the reference mic, the pair index and sign giving each mic's time, and the candidate rank.

    Returns
    -------
    pair_of : (H, M) int
        Pair index (i < j) that defines mic m's arrival time relative to the reference (−1 for the reference).
    sign : (H, M) float
        +1 where t_m − t_r = τ_pair, −1 where t_m − t_r = −τ_pair, 0 for the reference.
    rank : (H, M) int
        Candidate rank used for each mic (0 for the reference).
    """
    pairs = _pairs(n_mics)
    index = {p: n for n, p in enumerate(pairs)}
    rows_pair, rows_sign, rows_rank = [], [], []
    for ref in range(n_mics):
        others = [m for m in range(n_mics) if m != ref]
        for combo in itertools.product(range(k), repeat=n_mics - 1):
            pair_of = np.full(n_mics, -1)
            sign = np.zeros(n_mics)
            rank = np.zeros(n_mics, dtype=int)
            for m, c in zip(others, combo, strict=True):
                pair_of[m] = index[(min(ref, m), max(ref, m))]
                sign[m] = 1.0 if ref < m else -1.0
                rank[m] = c
            rows_pair.append(pair_of)
            rows_sign.append(sign)
            rows_rank.append(rank)
    return np.array(rows_pair), np.array(rows_sign), np.array(rows_rank)


class ConsistentSetSolver:
    """Jointly consistent GCC candidates over all mic pairs, the mics to trust, then the fix (module docstring).

    Parameters
    ----------
    tolerance_s : float
        Closure tolerance, s: a pair agrees with a hypothesis when one of its candidate lags is
        this close to the lag the hypothesis implies (about the width of a GCC peak).
    source_height_m : float, optional
        Height to assume, m; None takes ``SolverInputs.source_height_m`` (the site's mid height).
    max_hypotheses : int
        Upper bound on hypotheses per event; fewer candidates per pair are used above it.
    chunk_events : int
        Events evaluated together (bounds memory: chunk × hypotheses × pairs × candidates).
    n_iterations : int
        Levenberg–Marquardt iterations of the position polish.
    """

    cache_version = "1"
    required_feature_groups = ("tdoa",)

    def __init__(self, source_height_m: float | None = None, tolerance_s: float = 2.5e-4, max_hypotheses: int = 2000,
                 chunk_events: int = 16, n_iterations: int = 10) -> None:
        if tolerance_s <= 0:
            raise ConfigError(f"solver.tolerance_s must be > 0; got {tolerance_s}")
        if max_hypotheses < 1 or chunk_events < 1:
            raise ConfigError(f"solver.max_hypotheses and solver.chunk_events must be >= 1; got {max_hypotheses}, {chunk_events}")
        self.source_height_m = source_height_m
        self.tolerance_s = float(tolerance_s)
        self.max_hypotheses = int(max_hypotheses)
        self.chunk_events = int(chunk_events)
        self.n_iterations = int(n_iterations)

    # --- candidate selection ------------------------------------------------------------

    def select(self, candidates_s: np.ndarray, weights: np.ndarray) -> dict[str, np.ndarray]:
        """Choose the consistent set for events with (B, P, K) candidate lags and GCC heights.

        Returns a dict with ``times_s`` (B, M) fitted arrival times (NaN for untrusted mics),
        ``trusted`` (B, M) bool, and the per-event diagnostics of the module docstring.
        """
        bsz, n_pairs, k_all = candidates_s.shape
        m = int(round((1 + np.sqrt(1 + 8 * n_pairs)) / 2))
        pairs = _pairs(m)
        if len(pairs) != n_pairs:
            raise ValueError(f"pair_lag_candidates_s must cover all {len(pairs)} pairs of {m} mics; got {n_pairs}")
        k = k_all
        while k > 1 and m * k ** (m - 1) > self.max_hypotheses:
            k -= 1
        pair_of, sign, rank = _hypothesis_design(m, k)
        i_idx = np.array([p[0] for p in pairs])
        j_idx = np.array([p[1] for p in pairs])
        cands = candidates_s[:, :, :k_all]
        w = np.where(np.isfinite(cands), np.nan_to_num(weights, nan=0.0), 0.0)
        safe_pair = np.maximum(pair_of, 0)
        # (B, H, M) arrival times relative to each hypothesis' reference mic
        times = sign[None] * cands[:, safe_pair, rank]
        times = np.where(pair_of[None] < 0, 0.0, times)
        valid = np.isfinite(times).all(-1)
        predicted = times[..., j_idx] - times[..., i_idx]  # (B, H, P)
        # one candidate rank at a time: (B, H, P) temporaries instead of (B, H, P, K)
        pair_weight = np.zeros(predicted.shape)
        consistent = np.zeros(predicted.shape, dtype=bool)
        for r in range(k_all):
            close = np.abs(predicted - cands[:, None, :, r]) < self.tolerance_s
            consistent |= close
            np.maximum(pair_weight, close * w[:, None, :, r], out=pair_weight)
        # earliest arrivals break ties: a reflection only ever delays a mic
        lateness = (times - times.min(axis=-1, keepdims=True)).sum(axis=-1)  # NaN for invalid hypotheses, excluded below
        score = pair_weight.sum(-1) - 1e-3 * np.nan_to_num(lateness, nan=1e3)
        score = np.where(valid, score, -np.inf)
        best = np.argmax(score, axis=1)
        rows = np.arange(bsz)
        best_times = times[rows, best]  # (B, M)
        # hypotheses from different reference mics differ by a constant: compare times relative to mic 0
        relative = times - times[..., :1]
        distinct = np.abs(relative - relative[rows, best][:, None]).max(-1) > self.tolerance_s
        runner_up = np.where(distinct & valid, score, -np.inf).max(axis=1)
        margin = np.where(np.isfinite(runner_up), score[rows, best] - runner_up, np.nan)

        ok = consistent[rows, best]  # (B, P)
        per_mic = np.zeros((bsz, m))
        np.add.at(per_mic, (slice(None), i_idx), ok.astype(float))
        np.add.at(per_mic, (slice(None), j_idx), ok.astype(float))
        trusted = per_mic >= min(2, m - 1)
        too_few = trusted.sum(1) < 3
        trusted[too_few] = True  # with fewer than three trusted mics keep them all (and say so via consistency)
        pair_trusted = trusted[:, i_idx] & trusted[:, j_idx]
        use = ok & pair_trusted
        gap = np.abs(cands - predicted[rows, best][..., None])
        chosen_rank = np.argmin(np.where(np.isnan(gap), np.inf, gap), axis=-1)  # (B, P), missing peaks never chosen
        chosen = np.take_along_axis(cands, chosen_rank[..., None], -1)[..., 0]
        fitted = self._fit_times(chosen, use, trusted, best_times, i_idx, j_idx)
        resid = (fitted[:, j_idx] - fitted[:, i_idx]) - chosen
        n_use = use.sum(1)
        closure = np.sqrt(np.where(use, resid**2, 0.0).sum(1) / np.maximum(n_use, 1))
        return {
            "times_s": np.where(trusted, fitted, np.nan),
            "trusted": trusted,
            "consistent_pairs": ok.sum(1).astype(float),
            "consistency": n_use / np.maximum(pair_trusted.sum(1), 1),
            "score_margin": margin,
            "n_mics_used": trusted.sum(1).astype(float),
            "closure_rms_s": np.where(n_use > 0, closure, np.nan),
        }

    @staticmethod
    def _fit_times(lags: np.ndarray, use: np.ndarray, trusted: np.ndarray, fallback: np.ndarray, i_idx: np.ndarray, j_idx: np.ndarray) -> np.ndarray:
        """Least-squares arrival times from the used pair lags (B, P), batched normal equations (sum of times = 0)."""
        bsz, m = trusted.shape
        incidence = np.zeros((len(i_idx), m))
        incidence[np.arange(len(i_idx)), i_idx] = -1.0
        incidence[np.arange(len(i_idx)), j_idx] = 1.0
        wgt = use.astype(float)
        normal = np.einsum("bp,pm,pn->bmn", wgt, incidence, incidence) + np.ones((m, m)) / m
        rhs = np.einsum("bp,pm->bm", wgt * np.nan_to_num(lags), incidence)
        # a mic with no used pair keeps the hypothesis' time (it is not trusted anyway)
        lonely = np.einsum("bp,pm->bm", wgt, np.abs(incidence)) == 0
        eye = np.eye(m)
        normal = np.where(lonely[:, :, None] & (eye[None] > 0), normal + 1.0, normal)
        rhs = np.where(lonely, rhs + np.nan_to_num(fallback - np.nanmean(fallback, axis=1, keepdims=True)), rhs)
        return np.linalg.solve(normal, rhs[..., None])[..., 0]

    # --- solving --------------------------------------------------------------------------

    def solve(self, inputs: SolverInputs) -> SolverResult:
        """See :class:`acoustlab.core.contracts.Solver`; uses ``pair_lag_candidates_s`` (and weights) when present."""
        mics, tdoa, c, height = solver_inputs(inputs, self.source_height_m)
        base = HyperbolicSolver(source_height_m=height, n_iterations=self.n_iterations)
        if inputs.pair_lag_candidates_s is None:
            result = base.solve(inputs)
            for name in EXTRA_DIAGNOSTICS:
                result.diagnostics[name] = np.full(tdoa.shape[0], np.nan)
            return result
        cands = np.asarray(inputs.pair_lag_candidates_s, dtype=float)
        weights = np.ones_like(cands) if inputs.pair_lag_weights is None else np.asarray(inputs.pair_lag_weights, dtype=float)
        parts = [self.select(cands[s : s + self.chunk_events], weights[s : s + self.chunk_events])
                 for s in range(0, cands.shape[0], self.chunk_events)]
        chosen = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
        return self._solve_subsets(base, mics, chosen, c, inputs.received_level_db)

    def _solve_subsets(self, base: HyperbolicSolver, mics: np.ndarray, chosen: dict[str, np.ndarray], c: np.ndarray,
                       levels: np.ndarray | None) -> SolverResult:
        """Solve each group of events that trusts the same mics in one batch."""
        trusted = chosen["trusted"]
        bsz, m = trusted.shape
        position = np.full((bsz, 2), np.nan)
        residual = np.full(bsz, np.nan)
        converged = np.zeros(bsz, dtype=bool)
        diagnostics: dict[str, np.ndarray] = {}
        masks, group = np.unique(trusted, axis=0, return_inverse=True)
        for g, mask in enumerate(masks):
            rows = np.flatnonzero(group.ravel() == g)
            sub = np.flatnonzero(mask)
            times = chosen["times_s"][np.ix_(rows, sub)]
            sub_inputs = SolverInputs(mics[sub], times - times[:, :1], c[rows],
                                      received_level_db=None if levels is None else np.asarray(levels, dtype=float)[np.ix_(rows, sub)])
            result = base.solve(sub_inputs)
            position[rows] = result.position_m
            residual[rows] = result.residual_m
            converged[rows] = result.converged
            for name, values in result.diagnostics.items():
                diagnostics.setdefault(name, np.full(bsz, np.nan))[rows] = values
        for name in EXTRA_DIAGNOSTICS:
            diagnostics[name] = chosen[name]
        return SolverResult(position_m=position, residual_m=residual, converged=converged, diagnostics=diagnostics)
