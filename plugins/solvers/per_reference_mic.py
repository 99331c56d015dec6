"""Per-reference-mic solver: one fix per reference mic, keep the lowest residual (a peer heuristic).

OpenSoundscape's localization (as its documentation describes it) estimates one position per
reference receiver from that receiver's pairwise TDOAs and keeps the best-fitting one. This
plugin re-implements that idea from the description for side-by-side comparisons: for every
reference mic r the TDOAs t_m − t_r come from the highest GCC peak of the pairs (r, m); each set
is solved with the closed form and polish of ``plugins.solvers.hyperbolic.HyperbolicSolver``
(mics reordered so r comes first) and the fix with the smallest RMS range-difference residual
wins. With three mics every set fits exactly, so the choice is by the order of the mics.
"""

from __future__ import annotations

import numpy as np

from acoustlab.core.contracts import SolverInputs, SolverResult
from acoustlab.toolkit.tdoa import solver_inputs
from plugins.solvers.hyperbolic import HyperbolicSolver


class PerReferenceMicSolver:
    """See the module docstring.

    Parameters
    ----------
    source_height_m : float, optional
        Assumed source height in m (None: ``SolverInputs.source_height_m``).
    n_iterations : int
        Levenberg–Marquardt iterations of each fix.
    """

    cache_version = "1"
    required_feature_groups = ("tdoa",)

    def __init__(self, source_height_m: float | None = None, n_iterations: int = 30) -> None:
        self.source_height_m = source_height_m
        self.n_iterations = int(n_iterations)

    def solve(self, inputs: SolverInputs) -> SolverResult:
        """See ``acoustlab.core.contracts.Solver``; needs ``pair_lag_candidates_s`` for references other than mic 0."""
        mics, tdoa, c, height = solver_inputs(inputs, self.source_height_m)
        base = HyperbolicSolver(source_height_m=height, n_iterations=self.n_iterations)
        if inputs.pair_lag_candidates_s is None:
            return base.solve(inputs)
        m = mics.shape[0]
        pairs = [(i, j) for i in range(m) for j in range(i + 1, m)]
        top = np.asarray(inputs.pair_lag_candidates_s, dtype=float)[:, :, 0]  # (B, P) highest peak, t_j − t_i
        results = []
        for ref in range(m):
            order = [ref] + [k for k in range(m) if k != ref]
            lags = [0.0 * top[:, 0]] + [top[:, pairs.index((min(ref, k), max(ref, k)))] * (1.0 if ref < k else -1.0) for k in order[1:]]
            levels = None if inputs.received_level_db is None else np.asarray(inputs.received_level_db, dtype=float)[:, order]
            results.append(base.solve(SolverInputs(mics[order], np.column_stack(lags), c, received_level_db=levels)))
        residual = np.stack([np.where(np.isfinite(r.residual_m), r.residual_m, np.inf) for r in results], axis=1)
        best = np.argmin(residual, axis=1)
        rows = np.arange(len(best))
        pick = lambda values: np.stack(values, axis=1)[rows, best]  # noqa: E731
        diagnostics = {name: pick([r.diagnostics[name] for r in results]) for name in results[0].diagnostics}
        diagnostics["reference_mic"] = best.astype(float)
        return SolverResult(
            position_m=pick([r.position_m for r in results]),
            residual_m=pick([r.residual_m for r in results]),
            converged=pick([r.converged for r in results]),
            diagnostics=diagnostics,
        )
