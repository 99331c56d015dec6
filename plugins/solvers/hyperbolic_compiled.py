"""The closed-form hyperbolic solver compiled per event (``solver=hyperbolic_compiled``): the same fixes to within the polish's tolerance, faster.

:class:`CompiledHyperbolicSolver` takes :class:`~plugins.solvers.hyperbolic.HyperbolicSolver`'s
parameters and reports the same positions, residuals and diagnostics; the maths runs in
:mod:`acoustlab.toolkit.compiled_fix` (numba) instead of batched numpy. The positions agree with
the numpy solver's to within the polish's tolerance, not bit for bit (``tests/test_compiled_solver.py``;
``benchmarks/results/solver_speed.md`` times both).
"""

from __future__ import annotations

from acoustlab.core.contracts import SolverInputs, SolverResult
from acoustlab.toolkit.tdoa import solver_inputs
from plugins.solvers.hyperbolic import HyperbolicSolver

#: Diagnostics reported per mode, as the numpy solver reports them.
_DIAGNOSTICS = {2: ("residual_s", "conditioning", "gdop", "n_roots", "source_height_m"),
                3: ("residual_s", "gdop", "n_roots", "source_height_m", "height_gdop", "height_ambiguous", "dimensions_used")}


class CompiledHyperbolicSolver(HyperbolicSolver):
    """:class:`~plugins.solvers.hyperbolic.HyperbolicSolver` with its per-event maths compiled (module docstring)."""

    def solve(self, inputs: SolverInputs) -> SolverResult:
        """See :class:`acoustlab.core.contracts.Solver`; ``inputs.received_level_db`` enables energy disambiguation."""
        from acoustlab.toolkit.compiled_fix import solve_compiled  # imports numba: only when a compiled solver runs

        mics, tdoa, c, height = solver_inputs(inputs, self.source_height_m)
        if self.dimensions == 3 and mics.shape[0] < 4:
            raise ValueError(f"solver.dimensions=3 needs at least 4 mics; this array has {mics.shape[0]} (use dimensions=2)")
        fix = solve_compiled(mics, tdoa, c, height, inputs.received_level_db, dimensions=self.dimensions, fallback_2d=self.fallback_2d,
                             box_margin_fraction=self.box_margin_fraction, residual_tie_m=self.residual_tie_m, n_iterations=self.n_iterations)
        return SolverResult(position_m=fix["position_m"], residual_m=fix["residual_m"], converged=fix["converged"],
                            diagnostics={name: fix[name] for name in _DIAGNOSTICS[self.dimensions]})
