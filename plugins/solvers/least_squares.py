"""Batch least-squares TDOA solver (Levenberg–Marquardt from several starts), vectorised in NumPy.

Written by hand rather than with ``scipy.optimize.least_squares`` because that solves one
event per call (≈4 ms each); here every event and every start point iterate together as arrays.
"""

from __future__ import annotations

import numpy as np

from acoustlab.core.contracts import SolverInputs, SolverResult
from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.geometry import gdop
from acoustlab.toolkit.tdoa import levenberg_marquardt, solver_inputs
from plugins.solvers.hyperbolic import drop_undetermined


class LeastSquaresSolver:
    """2-D source position minimising range-difference residuals to mic 0.

    Residual of mic j for a candidate p: (‖p − m_j‖ − ‖p − m_0‖) − c·τ_j, with 3-D distances (known mic
    heights, an assumed source height). Starts from the array centroid, from points near each mic inside
    the array and from points beyond each mic, keeps the start with the smallest final residual.

    Parameters
    ----------
    source_height_m : float, optional
        Assumed source height in m; None uses ``SolverInputs.source_height_m`` (the site's mid
        source height), else the mean mic height.
    n_iterations : int
        Levenberg–Marquardt iterations.
    tolerance_m : float
        Step size below which an event counts as converged, in m.
    tie_tolerance_m : float
        RMS residual difference (m) within which two fits count as equally good.
    """

    cache_version = "1"
    required_feature_groups = ("tdoa",)

    def __init__(
        self, source_height_m: float | None = None, n_iterations: int = 100, tolerance_m: float = 1e-4, tie_tolerance_m: float = 0.05
    ) -> None:
        if n_iterations < 1:
            raise ConfigError(f"solver.n_iterations must be >= 1; got {n_iterations}")
        self.source_height_m = source_height_m
        self.n_iterations = int(n_iterations)
        self.tolerance_m = float(tolerance_m)
        self.tie_tolerance_m = float(tie_tolerance_m)

    @staticmethod
    def _starts(mics_xy: np.ndarray) -> np.ndarray:
        centroid = mics_xy.mean(axis=0)
        near = mics_xy + 0.25 * (centroid - mics_xy)  # inside the array, near each mic
        beyond = mics_xy + 0.5 * (mics_xy - centroid)  # outside, beyond each mic
        return np.vstack([centroid[None], near, beyond])  # (S, 2)

    def solve(self, inputs: SolverInputs) -> SolverResult:
        """See ``acoustlab.core.contracts.Solver``."""
        mics, tdoa, c, height = solver_inputs(inputs, self.source_height_m)
        b = tdoa.shape[0]
        rd = (c[:, None] * (tdoa[:, 1:] - tdoa[:, :1]))[:, None, :]  # (B, 1, M-1)
        starts = self._starts(mics[:, :2])
        p0 = np.broadcast_to(starts, (b, starts.shape[0], 2))  # (B, S, 2)
        z = np.full(p0.shape[:2], height)
        p, cost, step_norm = levenberg_marquardt(p0, mics, z, rd, self.n_iterations)
        # Where several starts reach an equally good fit (the two roots of a 3-mic array), prefer
        # the one nearest the array centroid and report how many distinct fits there were.
        cost = np.where(np.isfinite(cost), cost, np.inf)
        tied = cost <= cost.min(axis=1, keepdims=True) + self.tie_tolerance_m**2 * (mics.shape[0] - 1)
        centre_dist = np.sqrt(((p - mics[:, :2].mean(axis=0)) ** 2).sum(-1))
        best = np.argmin(np.where(tied, centre_dist, np.inf), axis=1)
        rows = np.arange(b)
        spread = np.sqrt(((p - p[rows, best][:, None, :]) ** 2).sum(-1))
        n_roots = 1 + (tied & (spread > 1.0)).sum(axis=1)
        position = p[rows, best]
        residual = np.sqrt(cost[rows, best] / (mics.shape[0] - 1))
        converged = (step_norm[rows, best] < self.tolerance_m) | (residual < 1e-6)
        finite = np.isfinite(tdoa).all(axis=1) & np.isfinite(c)
        position[~finite] = np.nan
        residual[~finite] = np.nan
        converged &= finite
        geometry = np.full(b, np.nan)
        geometry[finite] = gdop(mics, np.column_stack([position[finite], np.full(finite.sum(), height)]))
        converged = converged & ~drop_undetermined(position, geometry, mics)
        return SolverResult(
            position_m=position,
            residual_m=residual,
            converged=converged,
            diagnostics={"gdop": geometry, "n_roots": n_roots.astype(float), "source_height_m": np.full(b, height)},
        )
