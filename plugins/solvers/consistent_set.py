"""Consistent-set TDOA solver: the jointly consistent GCC candidates over *all* mic pairs, and the mics to trust.

A reflection, a trunk-scattered path or a noise burst can outrank the direct path in one pair's
GCC. Choosing among the candidates of the pairs with one reference mic cannot fix that when the
reference mic itself is the corrupted one. This solver therefore looks at every pair:

1. **Hypotheses.** For every reference mic r and every choice of one of the K candidate lags of
   each pair (r, m), the arrival times t_m − t_r follow. That is M · K^(M−1) hypotheses per event
   (forest, 6 mics, K = 3: 1,458), scored together as arrays for a chunk of events; on larger
   arrays (12 mics: 2.1 million) an exact branch and bound finds the same best hypothesis while
   scoring a few dozen (``plugins.solvers.hypothesis_search``).
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
   (``plugins.solvers.hyperbolic.HyperbolicSolver``).

Diagnostics per event: ``consistent_pairs``, ``consistency`` (share of the pairs among trusted
mics that are consistent), ``score_margin`` (best minus runner-up score, in GCC-height units),
``n_mics_used`` and ``closure_rms_s`` (RMS misfit of the chosen lags to the fitted arrival times).
They are the cues a gate and an error model can use.
"""

from __future__ import annotations

import numpy as np

from acoustlab.core.contracts import MICS_USED_MASK, SolverInputs, SolverResult
from acoustlab.core.errors import ConfigError, DataError
from acoustlab.toolkit.tdoa import solver_inputs
from plugins.solvers.hyperbolic import HyperbolicSolver
from plugins.solvers.hypothesis_search import exhaustive_best, hypothesis_design, pair_layout, pairs_of, pruned_best

#: Largest number of hypotheses per event that ``search="auto"`` scores exhaustively: scoring every
#: hypothesis as one array wins while they are few (up to 8 mics × 3 candidates: 17,496); the branch
#: and bound, which scores a few dozen, wins from 10 mics (196,830) on. Both make the same choice.
EXHAUSTIVE_UP_TO = 20_000

#: Diagnostics this solver adds to the hyperbolic solver's (catalogued in ``acoustlab.core.columns.SOLVER_CATALOG``).
EXTRA_DIAGNOSTICS = ("consistent_pairs", "consistency", "score_margin", "n_mics_used", "closure_rms_s", MICS_USED_MASK)


def checked_weights(weights: np.ndarray, candidates_s: np.ndarray) -> np.ndarray:
    """``weights`` (the GCC heights of ``candidates_s``, (B, P, K)) as floats, or a ``DataError`` saying what is wrong with them.

    A NaN height counts as 0 and a missing candidate's height is not read, but an infinite height of
    a candidate that exists would make every score containing it infinite (or NaN beside another),
    so the choice would mean nothing: it stops, naming the first such event, pair and rank.
    """
    weights = np.asarray(weights, dtype=float)
    if weights.shape != candidates_s.shape:
        raise DataError(
            f"pair_lag_weights must have the shape of pair_lag_candidates_s {candidates_s.shape} (events, pairs, candidates); "
            f"got {weights.shape}"
        )
    if not np.isinf(weights).any():  # the usual case, in one pass
        return weights
    infinite = np.isinf(weights) & np.isfinite(candidates_s)
    if infinite.any():
        event, pair, rank = np.argwhere(infinite)[0]
        raise DataError(
            f"pair_lag_weights must be finite GCC heights (NaN counts as 0); got {weights[event, pair, rank]} at event {event}, "
            f"pair {pair}, candidate {rank} ({int(infinite.sum())} infinite heights in all)"
        )
    return weights


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
        Upper bound on hypotheses per event (M · K^(M−1)); fewer candidates per pair are used above it.
    chunk_events : int
        Events evaluated together (bounds memory: chunk × hypotheses × pairs × candidates).
    n_iterations : int
        Levenberg–Marquardt iterations of the position polish.
    dimensions : {2, 3, "auto"}
        2: x, y at the assumed height; 3: x, y and height where ≥ 4 mics are trusted (events
        with 3 trusted mics, or whose 3-D fix fails, fall back to the assumed height; their
        ``height_gdop`` is NaN); "auto": 3 for arrays of ≥ 4 mics, else 2.
    prior_weight : float
        Score-based agreement: with a prior position (SRP-PHAT's peak, ``features=physics_srp``)
        every pair whose hypothesised lag lies within ``prior_tolerance_s`` of the lag the prior
        implies adds this much to the hypothesis' score (GCC-height units, so 0.05 breaks near-ties
        only); 0 ignores the prior.
    prior_tolerance_s : float
        Tolerance of that agreement, s (the SRP grid's resolution in lag).
    search : {"auto", "pruned", "exhaustive"}
        How the best hypothesis is found: every hypothesis scored, or an exact branch and bound
        that scores a few dozen; both give the same choice, bit for bit
        (``plugins.solvers.hypothesis_search``). "auto" scores every one up to
        ``EXHAUSTIVE_UP_TO`` hypotheses per event (up to 8 mics with 3 candidates, where that
        is faster in numpy) and prunes above, where the exhaustive search's index arrays grow to
        gigabytes (12 mics: 2.1 million hypotheses × 66 pairs).
    """

    cache_version = "1"
    required_feature_groups = ("tdoa",)

    def __init__(
        self,
        source_height_m: float | None = None,
        tolerance_s: float = 2.5e-4,
        max_hypotheses: int = 10_000_000,
        chunk_events: int = 16,
        n_iterations: int = 30,
        dimensions: int | str = "auto",
        prior_weight: float = 0.0,
        prior_tolerance_s: float = 2e-3,
        search: str = "auto",
    ) -> None:
        if search not in ("auto", "pruned", "exhaustive"):
            raise ConfigError(f"solver.search must be 'auto', 'pruned' or 'exhaustive'; got {search!r}")
        self.search = search
        if tolerance_s <= 0:
            raise ConfigError(f"solver.tolerance_s must be > 0; got {tolerance_s}")
        if max_hypotheses < 1 or chunk_events < 1:
            raise ConfigError(f"solver.max_hypotheses and solver.chunk_events must be >= 1; got {max_hypotheses}, {chunk_events}")
        self.source_height_m = source_height_m
        self.tolerance_s = float(tolerance_s)
        self.max_hypotheses = int(max_hypotheses)
        self.chunk_events = int(chunk_events)
        self.n_iterations = int(n_iterations)
        if dimensions not in (2, 3, "auto"):
            raise ConfigError(f"solver.dimensions must be 2, 3 or auto; got {dimensions!r}")
        self.dimensions = dimensions if dimensions == "auto" else int(dimensions)
        if prior_weight < 0 or prior_tolerance_s <= 0:
            raise ConfigError(f"solver.prior_weight must be >= 0 and solver.prior_tolerance_s > 0; got {prior_weight}, {prior_tolerance_s}")
        self.prior_weight = float(prior_weight)
        self.prior_tolerance_s = float(prior_tolerance_s)

    # --- candidate selection ------------------------------------------------------------

    def select(self, candidates_s: np.ndarray, weights: np.ndarray, prior_lags_s: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Choose the consistent set for events with (B, P, K) candidate lags and GCC heights.

        The score of a hypothesis is a sum over pairs of a term that depends only on the candidate
        ranks of the pair's two mics (for the hypothesis' reference). Each pair's (K × K) table of
        those terms is built once per reference, so scoring all hypotheses is one gather and one
        sum instead of comparing every hypothesis with every candidate.

        ``prior_lags_s`` (B, P): the pair lags an independent estimate implies; hypotheses agreeing
        with them gain ``prior_weight`` per pair.

        Returns a dict with ``times_s`` (B, M) fitted arrival times (NaN for untrusted mics),
        ``trusted`` (B, M) bool, and the per-event diagnostics of the module docstring.
        """
        bsz, n_pairs, k_all = candidates_s.shape
        m, k = self._search_shape(n_pairs, k_all)
        layout = pair_layout(m)
        i_idx, j_idx = layout.i_idx, layout.j_idx
        cands = candidates_s
        w = np.where(np.isfinite(cands), np.nan_to_num(weights, nan=0.0), 0.0)
        # per reference r and mic n: the K candidate arrival times t_n − t_r (0 for n = r)
        signed = layout.ref_sign[None, :, :, None] * cands[:, layout.ref_pair, :k]  # (B, R, M, K)
        arrival = np.where(layout.ref_pair[None, :, :, None] < 0, 0.0, signed)
        # table[b, r, p, a, c]: weight of pair p=(i, j) when mic i takes rank a and mic j rank c
        predicted = arrival[:, :, j_idx, None, :] - arrival[:, :, i_idx, :, None]  # (B, R, P, K, K)
        table = np.zeros(predicted.shape)
        for r in range(k_all):
            close = np.abs(predicted - cands[:, None, :, None, None, r]) < self.tolerance_s
            np.maximum(table, close * w[:, None, :, None, None, r], out=table)
        if prior_lags_s is not None and self.prior_weight > 0:
            agrees = np.abs(predicted - prior_lags_s[:, None, :, None, None]) < self.prior_tolerance_s  # NaN priors never agree
            table = table + self.prior_weight * agrees
        # a hypothesis using a missing arrival time scores −inf: every pair touching that arrival does
        missing = ~np.isfinite(arrival)  # (B, R, M, K)
        table = np.where(missing[:, :, i_idx, :, None] | missing[:, :, j_idx, None, :], -np.inf, table)
        search = self.search if self.search != "auto" else ("exhaustive" if m * k ** (m - 1) <= EXHAUSTIVE_UP_TO else "pruned")
        if search == "pruned":
            best_times, margin = pruned_best(table, arrival, layout, self.tolerance_s)
        else:
            best_times, margin = exhaustive_best(table, arrival, hypothesis_design(m, k), self.tolerance_s)

        best_predicted = best_times[:, j_idx] - best_times[:, i_idx]  # (B, P)
        gap = np.abs(cands - best_predicted[..., None])
        ok = (gap < self.tolerance_s).any(-1)  # (B, P); NaN gaps compare False
        per_mic = np.zeros((bsz, m))
        np.add.at(per_mic, (slice(None), i_idx), ok.astype(float))
        np.add.at(per_mic, (slice(None), j_idx), ok.astype(float))
        trusted = per_mic >= min(2, m - 1)
        too_few = trusted.sum(1) < 3
        trusted[too_few] = True  # with fewer than three trusted mics keep them all (and say so via consistency)
        pair_trusted = trusted[:, i_idx] & trusted[:, j_idx]
        use = ok & pair_trusted
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
            # which mics, as bits (mic m: 2^m): the positions table lists them (it is no feature: acoustlab.stages.solver_columns)
            MICS_USED_MASK: (trusted * 2.0 ** np.arange(m)).sum(1),
            "closure_rms_s": np.where(n_use > 0, closure, np.nan),
        }

    def _search_shape(self, n_pairs: int, k_all: int) -> tuple[int, int]:
        """The mics M whose pairs the P = ``n_pairs`` candidates cover, and the candidates per pair k ≤ K = ``k_all`` that form
        hypotheses (the most whose M · k^(M−1) hypotheses stay within ``max_hypotheses``)."""
        m = int(round((1 + np.sqrt(1 + 8 * n_pairs)) / 2))
        if len(pairs_of(m)) != n_pairs:
            raise ValueError(f"pair_lag_candidates_s must cover all {len(pairs_of(m))} pairs of {m} mics; got {n_pairs}")
        k = k_all
        while k > 1 and m * k ** (m - 1) > self.max_hypotheses:
            k -= 1
        return m, k

    @staticmethod
    def _fit_times(
        lags: np.ndarray, use: np.ndarray, trusted: np.ndarray, fallback: np.ndarray, i_idx: np.ndarray, j_idx: np.ndarray
    ) -> np.ndarray:
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
        """See ``acoustlab.core.contracts.Solver``; uses ``pair_lag_candidates_s`` (and weights) when present."""
        mics, tdoa, c, height = solver_inputs(inputs, self.source_height_m)
        dimensions = (3 if len(mics) >= 4 else 2) if self.dimensions == "auto" else self.dimensions
        base = HyperbolicSolver(source_height_m=height, n_iterations=self.n_iterations, dimensions=dimensions)
        if inputs.pair_lag_candidates_s is None:
            result = base.solve(inputs)
            for name in EXTRA_DIAGNOSTICS:
                result.diagnostics[name] = np.full(tdoa.shape[0], np.nan)
            return result
        cands = np.asarray(inputs.pair_lag_candidates_s, dtype=float)
        weights = np.ones_like(cands) if inputs.pair_lag_weights is None else checked_weights(inputs.pair_lag_weights, cands)
        prior = self._prior_lags(inputs, mics, c, height)
        parts = [
            self.select(
                cands[s : s + self.chunk_events],
                weights[s : s + self.chunk_events],
                None if prior is None else prior[s : s + self.chunk_events],
            )
            for s in range(0, cands.shape[0], self.chunk_events)
        ]
        chosen = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
        return self._solve_subsets(base, mics, chosen, c, inputs.received_level_db)

    def _prior_lags(self, inputs: SolverInputs, mics: np.ndarray, c: np.ndarray, height: float) -> np.ndarray | None:
        """(B, P) pair lags t_j − t_i implied by ``inputs.prior_position_m`` at the assumed height (None without a prior)."""
        if inputs.prior_position_m is None or self.prior_weight == 0:
            return None
        prior = np.asarray(inputs.prior_position_m, dtype=float)
        src = np.column_stack([prior, np.full(len(prior), height)])
        t = np.sqrt(((src[:, None, :] - mics[None]) ** 2).sum(-1)) / c[:, None]
        return np.stack([t[:, j] - t[:, i] for i, j in pairs_of(len(mics))], axis=1)

    @staticmethod
    def _groups_by_trusted(trusted: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each distinct row of ``trusted`` (B, M) with the events (row indices, ascending) that have it, rows in lexicographic order."""
        masks, group = np.unique(trusted, axis=0, return_inverse=True)
        return [(mask, np.flatnonzero(group.ravel() == g)) for g, mask in enumerate(masks)]

    def _solve_subsets(
        self, base: HyperbolicSolver, mics: np.ndarray, chosen: dict[str, np.ndarray], c: np.ndarray, levels: np.ndarray | None
    ) -> SolverResult:
        """Solve each group of events that trusts the same mics in one batch."""
        trusted = chosen["trusted"]
        bsz, m = trusted.shape
        position = np.full((bsz, 2), np.nan)
        residual = np.full(bsz, np.nan)
        converged = np.zeros(bsz, dtype=bool)
        diagnostics: dict[str, np.ndarray] = {}
        for mask, rows in self._groups_by_trusted(trusted):
            sub = np.flatnonzero(mask)
            times = chosen["times_s"][np.ix_(rows, sub)]
            sub_inputs = SolverInputs(
                mics[sub],
                times - times[:, :1],
                c[rows],
                received_level_db=None if levels is None else np.asarray(levels, dtype=float)[np.ix_(rows, sub)],
            )
            solver = (
                base
                if base.dimensions == 2 or len(sub) >= 4
                else HyperbolicSolver(source_height_m=base.source_height_m, n_iterations=base.n_iterations)
            )  # 3 mics: height assumed
            result = solver.solve(sub_inputs)
            position[rows] = result.position_m
            residual[rows] = result.residual_m
            converged[rows] = result.converged
            for name, values in result.diagnostics.items():
                diagnostics.setdefault(name, np.full(bsz, np.nan))[rows] = values
        if "dimensions_used" in diagnostics:  # groups solved in 2-D (3 trusted mics) have no 3-D diagnostics
            diagnostics["dimensions_used"] = np.where(np.isnan(diagnostics["dimensions_used"]), 2.0, diagnostics["dimensions_used"])
        for name in EXTRA_DIAGNOSTICS:
            diagnostics[name] = chosen[name]
        return SolverResult(position_m=position, residual_m=residual, converged=converged, diagnostics=diagnostics)
