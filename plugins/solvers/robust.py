"""Robust multi-candidate TDOA solver: the most mutually consistent set of GCC peak candidates.

Where the dominant GCC peak of a pair is a reflection or noise, one of its lower-ranked peaks is
often the direct path. Every combination of candidates for the pairs (0, j) is a hypothesis; each
is solved in closed form, and scored by how many of *all* mic pairs have a candidate lag within
``tolerance_s`` of the lag the hypothesis predicts (a consensus, as in RANSAC). The hypothesis with
the most consistent pairs wins (ties: smaller residual).
"""

from __future__ import annotations

import itertools

import numpy as np

from acoustlab.core.contracts import SolverInputs, SolverResult
from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.tdoa import solver_inputs
from plugins.solvers.hyperbolic import HyperbolicSolver


class ConsistentCandidatesSolver:
    """See the module docstring.

    Parameters
    ----------
    source_height_m : float, optional
        Assumed source height in m (None: ``SolverInputs.source_height_m``, the site's mid height).
    tolerance_s : float
        A pair is consistent when one of its candidate lags is this close to the predicted lag, s.
    max_hypotheses : int
        Upper bound on candidate combinations per event (fewer candidates per pair are used above it).
    """

    cache_version = "1"
    required_feature_groups = ("tdoa",)

    def __init__(self, source_height_m: float | None = None, tolerance_s: float = 2.5e-4, max_hypotheses: int = 729) -> None:
        if tolerance_s <= 0:
            raise ConfigError(f"solver.tolerance_s must be > 0; got {tolerance_s}")
        self.source_height_m = source_height_m
        self.tolerance_s = float(tolerance_s)
        self.max_hypotheses = int(max_hypotheses)

    def solve(self, inputs: SolverInputs) -> SolverResult:
        """See ``acoustlab.core.contracts.Solver``; ``inputs.pair_lag_candidates_s`` is (B, P, K) over the pairs i < j."""
        mics, _, c, height = solver_inputs(inputs, self.source_height_m)
        base = HyperbolicSolver(source_height_m=height, n_iterations=10)
        received_level_db, pair_lag_candidates_s = inputs.received_level_db, inputs.pair_lag_candidates_s
        if pair_lag_candidates_s is None:
            return base.solve(inputs)
        m = mics.shape[0]
        pairs = [(i, j) for i in range(m) for j in range(i + 1, m)]
        cands = np.asarray(pair_lag_candidates_s, dtype=float)
        bsz, n_pairs, k = cands.shape
        if n_pairs != len(pairs):
            raise ValueError(f"pair_lag_candidates_s must have {len(pairs)} pairs; got {n_pairs}")
        while k > 1 and k ** (m - 1) > self.max_hypotheses:
            k -= 1
        ref_pairs = [pairs.index((0, j)) for j in range(1, m)]
        combos = np.array(list(itertools.product(range(k), repeat=m - 1)))  # (H, M-1)
        h = combos.shape[0]
        lags = cands[:, ref_pairs, :k]  # (B, M-1, k)
        hyp = np.take_along_axis(lags[:, None, :, :], combos[None, :, :, None], -1)[..., 0]  # (B, H, M-1)
        tdoa = np.concatenate([np.zeros((bsz, h, 1)), hyp], axis=-1).reshape(bsz * h, m)
        levels = None if received_level_db is None else np.repeat(np.asarray(received_level_db, dtype=float), h, axis=0)
        res = base.solve(SolverInputs(mics, np.nan_to_num(tdoa, nan=0.0), np.repeat(c, h), received_level_db=levels))
        pos = res.position_m.reshape(bsz, h, 2)
        height = res.diagnostics["source_height_m"].reshape(bsz, h)
        src = np.concatenate([pos, height[..., None]], axis=-1)
        dist = np.sqrt(((src[..., None, :] - mics) ** 2).sum(-1))  # (B, H, M)
        i_idx = np.array([p[0] for p in pairs])
        j_idx = np.array([p[1] for p in pairs])
        predicted = (dist[..., j_idx] - dist[..., i_idx]) / c[:, None, None]  # (B, H, P)
        close = np.abs(cands[:, None, :, :] - predicted[..., None]) < self.tolerance_s  # (B, H, P, K)
        support = close.any(-1).sum(-1).astype(float)  # consistent pairs per hypothesis
        valid = np.isfinite(tdoa.reshape(bsz, h, m)).all(-1) & np.isfinite(pos).all(-1)
        residual = res.residual_m.reshape(bsz, h)
        score = np.where(valid, support - 1e-3 * np.nan_to_num(residual, nan=1e3), -np.inf)
        best = np.argmax(score, axis=1)
        rows = np.arange(bsz)
        pick = rows * h + best
        diag = {name: np.asarray(v)[pick] for name, v in res.diagnostics.items()}
        diag["consistent_pairs"] = support[rows, best]
        diag["hypotheses"] = np.full(bsz, float(h))
        return SolverResult(position_m=pos[rows, best], residual_m=residual[rows, best], converged=res.converged[pick], diagnostics=diag)
