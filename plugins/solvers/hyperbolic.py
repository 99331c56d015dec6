"""Closed-form hyperbolic (TDOA) solver with explicit root disambiguation and LM refinement.

With mic 0's horizontal position as origin, q_j the other mics, h_j = z_s − z_j (assumed source
height, known mic heights) and range differences d_j = c (t_j − t_0), squaring
r_j = r_0 + d_j gives the linear system −2 q_j·p − 2 d_j r_0 = d_j² − |q_j|² − h_j² + h_0². Its
least-squares solution in p for a given r_0 is p = u + v r_0; substituting into r_0² = |p|² + h_0²
gives a quadratic in r_0 with up to two positive roots — the two branches where hyperbolas meet.
The root is chosen explicitly: smaller TDOA residual (decisive with ≥ 4 mics), then inside the
plausibility box, then energy consistency with the received levels; every event reports how many
roots there were. The chosen root is refined by Levenberg–Marquardt on all range differences.
"""

from __future__ import annotations

import logging

import numpy as np

from acoustlab.core.contracts import SolverInputs, SolverResult
from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.geometry import bounding_box, gdop
from acoustlab.toolkit.solve3d import solve_3d
from acoustlab.toolkit.tdoa import (
    energy_residual_db,
    levenberg_marquardt,
    range_residuals,
    solver_inputs,
)

log = logging.getLogger(__name__)


def drop_undetermined(position: np.ndarray, geometry: np.ndarray, mics: np.ndarray) -> np.ndarray:
    """With every mic on one line, set to NaN, in place, the fixes the geometry does not determine (GDOP infinite); return where.

    A source off the mics' line has a mirror image across it that fits the time differences as well,
    and a least-squares fit lands between the two, on the line, fitting neither; there GDOP is
    infinite. Such a fix is reported as none (NaN, ``solver__failure`` 1) with a warning, never as a
    point. On other arrays an infinite GDOP marks an isolated ill-conditioned spot (a baseline's
    extension), where the fix can still be close: it is kept, and the learned models see the GDOP as missing.
    """
    centred = mics[:, :2] - mics[:, :2].mean(axis=0)
    collinear = np.linalg.matrix_rank(centred, tol=1e-6 * max(float(np.abs(centred).max()), 1e-12)) < 2
    undetermined = collinear & np.isfinite(position).all(axis=1) & ~np.isfinite(geometry)
    if undetermined.any():
        log.warning(
            "solver: %d of %d fixes are not determined: the mics lie on one line, so a source off it has a mirror image; "
            "reported as no fix (add a mic off the line)",
            int(undetermined.sum()),
            len(position),
        )
        position[undetermined] = np.nan
    return undetermined


class HyperbolicSolver:
    """Batch closed-form TDOA solver (see the module docstring).

    Parameters
    ----------
    source_height_m : float, optional
        Assumed source height in m; None uses ``SolverInputs.source_height_m`` (the site's mid
        source height), else the mean mic height.
    box_margin_fraction : float
        Plausibility box: the mics' bounding box grown by this fraction of the array extent.
    residual_tie_m : float
        Roots whose RMS residuals differ by less than this (m) count as equally good fits.
    n_iterations : int
        Levenberg–Marquardt iterations after the closed form.
    dimensions : int
        2: solve x, y at the assumed source height. 3: solve x, y and the height as well
        (≥ 4 mics; ``acoustlab.toolkit.solve3d``); ``source_height_m`` then reports the
        estimate, with ``height_gdop`` and ``height_ambiguous`` beside it. Where the 3-D fix fails
        or is implausible the 2-D fix replaces it (``dimensions_used``).
    fallback_2d : bool
        With ``dimensions=3``: replace a 3-D fix that fails, lies below ground or outside the mics'
        box grown by the array extent with the 2-D fix (default). False keeps every 3-D fix, e.g.
        for a bird aloft and far outside a small array, or to check TDOAs by leaving a receiver out.
    """

    cache_version = "1"
    required_feature_groups = ("tdoa",)

    def __init__(
        self,
        source_height_m: float | None = None,
        box_margin_fraction: float = 0.25,
        residual_tie_m: float = 0.05,
        n_iterations: int = 30,
        dimensions: int = 2,
        fallback_2d: bool = True,
    ) -> None:
        if n_iterations < 0:
            raise ConfigError(f"solver.n_iterations must be >= 0; got {n_iterations}")
        if dimensions not in (2, 3):
            raise ConfigError(f"solver.dimensions must be 2 or 3; got {dimensions}")
        self.dimensions = int(dimensions)
        self.source_height_m = source_height_m
        self.box_margin_fraction = float(box_margin_fraction)
        self.residual_tie_m = float(residual_tie_m)
        self.n_iterations = int(n_iterations)
        self.fallback_2d = bool(fallback_2d)

    def roots(self, mics: np.ndarray, rd: np.ndarray, height: float) -> tuple[np.ndarray, np.ndarray]:
        """Closed-form candidate positions (B, 2, 2) and their validity (B, 2) for range differences (B, M−1)."""
        origin = mics[0, :2]
        q = mics[1:, :2] - origin
        h = height - mics[:, 2]
        a_mat = -2 * q  # (M-1, 2)
        pinv = np.linalg.pinv(a_mat)  # (2, M-1)
        b = rd**2 - (q**2).sum(-1) - h[1:] ** 2 + h[0] ** 2  # (B, M-1)
        # einsum, not @: BLAS rounds a row differently by how many rows come with it, and a fix must not depend on its batch
        u = np.einsum("bk,jk->bj", b, pinv)  # (B, 2)
        v = np.einsum("bk,jk->bj", 2 * rd, pinv)  # (B, 2): p = u + v r0 since −g = 2 d
        a2 = (v**2).sum(-1) - 1
        a1 = 2 * (u * v).sum(-1)
        a0 = (u**2).sum(-1) + h[0] ** 2
        disc = a1**2 - 4 * a2 * a0
        sqrt_disc = np.sqrt(np.maximum(disc, 0))
        with np.errstate(divide="ignore", invalid="ignore"):
            linear = np.abs(a2) < 1e-12
            r_plus = np.where(linear, -a0 / a1, (-a1 + sqrt_disc) / (2 * a2))
            r_minus = np.where(linear, np.nan, (-a1 - sqrt_disc) / (2 * a2))
        # with a negative discriminant (noisy TDOAs) take the vertex: the closest approach
        vertex = np.where(linear, np.nan, -a1 / (2 * a2))
        r_plus = np.where(disc < 0, vertex, r_plus)
        r_minus = np.where(disc < 0, np.nan, r_minus)
        r0 = np.stack([r_plus, r_minus], axis=1)  # (B, 2)
        valid = np.isfinite(r0) & (r0 >= abs(h[0]) - 1e-6)
        cand = u[:, None, :] + v[:, None, :] * r0[..., None] + origin
        cand = np.where(valid[..., None], cand, np.nan)
        # two numerically identical roots count once
        same = valid[:, 1] & valid[:, 0] & (np.linalg.norm(cand[:, 0] - cand[:, 1], axis=-1) < 1e-6)
        valid[:, 1] &= ~same
        return cand, valid

    def solve(self, inputs: SolverInputs) -> SolverResult:
        """See ``acoustlab.core.contracts.Solver``; ``inputs.received_level_db`` enables energy disambiguation."""
        mics, tdoa, c, height = solver_inputs(inputs, self.source_height_m)
        received_level_db = inputs.received_level_db
        bsz = tdoa.shape[0]
        finite = np.isfinite(tdoa).all(axis=1) & np.isfinite(c)
        rd = np.where(finite[:, None], c[:, None] * (tdoa[:, 1:] - tdoa[:, :1]), 0.0)
        if self.dimensions == 3:
            fix3 = self._solve_3d(mics, rd, c, finite)
            if not self.fallback_2d:
                fix3.diagnostics["dimensions_used"] = np.where(np.isfinite(fix3.position_m).all(axis=1), 3.0, np.nan)
                return fix3
            return self._with_2d_fallback(fix3, inputs, mics)
        cand, valid = self.roots(mics, rd, height)
        n_roots = valid.sum(axis=1)

        # refine every valid root, then choose among the refined roots
        heights = np.full(valid.shape, height)
        refined = np.full(cand.shape, np.nan)
        cost = np.full(valid.shape, np.inf)
        step = np.full(valid.shape, np.inf)
        b_idx, r_idx = np.nonzero(valid)  # only real roots are refined
        refined[b_idx, r_idx], cost[b_idx, r_idx], step[b_idx, r_idx] = levenberg_marquardt(
            cand[b_idx, r_idx], mics, heights[b_idx, r_idx], rd[b_idx], self.n_iterations
        )
        residual = np.sqrt(cost / (mics.shape[0] - 1))
        residual = np.where(valid, residual, np.inf)
        low, high = bounding_box(mics, self.box_margin_fraction)
        inside = ((refined >= low) & (refined <= high)).all(-1) & valid
        score = np.where(valid, 0.0, np.inf)
        best_res = residual.min(axis=1, keepdims=True)
        worse_fit = residual > best_res + self.residual_tie_m
        score = score + worse_fit * 1e6 + (~inside) * 1e3
        if received_level_db is not None:
            energy = energy_residual_db(np.asarray(received_level_db, dtype=float), mics, refined, heights)
            score = score + np.nan_to_num(energy, nan=0.0)
        else:  # no levels: among equally good, plausible roots prefer the one nearer the array
            score = score + 1e-3 * np.linalg.norm(refined - mics[:, :2].mean(axis=0), axis=-1)
        none_valid = ~valid.any(axis=1)
        choice = np.argmin(np.where(np.isfinite(score), score, np.inf), axis=1)
        rows = np.arange(bsz)
        position = refined[rows, choice]
        res = residual[rows, choice]
        # fall back to LM from the centroid where the closed form gave nothing
        if none_valid.any():
            p_fb, cost_fb, _ = levenberg_marquardt(
                np.broadcast_to(mics[:, :2].mean(axis=0), (none_valid.sum(), 2)),
                mics,
                np.full(none_valid.sum(), height),
                rd[none_valid],
                max(self.n_iterations, 50),
            )
            position[none_valid] = p_fb
            res[none_valid] = np.sqrt(cost_fb / (mics.shape[0] - 1))
        converged = (step[rows, choice] < 1e-3) | (res < 1e-6)
        r, jac = range_residuals(position, mics, np.full(bsz, height), rd)
        # singular values of the (M−1, 2) Jacobian from the eigenvalues of the 2 × 2 JᵀJ, in closed form
        jtj = np.einsum("bki,bkj->bij", jac, jac)
        half_trace = (jtj[:, 0, 0] + jtj[:, 1, 1]) / 2
        spread = np.sqrt(((jtj[:, 0, 0] - jtj[:, 1, 1]) / 2) ** 2 + jtj[:, 0, 1] ** 2)
        conditioning = np.sqrt(np.maximum(half_trace + spread, 0) / np.maximum(half_trace - spread, 1e-24))
        position[~finite] = np.nan
        res = np.where(finite, res, np.nan)
        converged &= finite
        geometry = np.full(bsz, np.nan)
        geometry[finite] = gdop(mics, np.column_stack([position[finite], np.full(finite.sum(), height)]))
        converged &= ~drop_undetermined(position, geometry, mics)
        return SolverResult(
            position_m=position,
            residual_m=res,
            converged=converged,
            diagnostics={
                "residual_s": res / c,
                "conditioning": np.where(finite, conditioning, np.nan),
                "gdop": geometry,
                "n_roots": n_roots.astype(float),
                "source_height_m": np.full(bsz, height),
            },
        )

    def _with_2d_fallback(self, fix3: SolverResult, inputs: SolverInputs, mics: np.ndarray) -> SolverResult:
        """Where the 3-D fix failed, or lies below ground or outside the mics' box grown by the array extent, the 2-D fix
        at the assumed height replaces it (``solver__dimensions_used`` says which; the height is then the assumed one)."""
        low, high = bounding_box(mics, 1.0)
        xy, z = fix3.position_m, fix3.diagnostics["source_height_m"]
        usable = np.isfinite(xy).all(axis=1) & ((xy >= low) & (xy <= high)).all(axis=1) & (z >= 0)
        out = SolverResult(
            fix3.position_m.copy(),
            fix3.residual_m.copy(),
            fix3.converged.copy(),
            {**{k: np.array(v, dtype=float) for k, v in fix3.diagnostics.items()}, "dimensions_used": np.where(usable, 3.0, 2.0)},
        )
        if usable.all():
            return out
        fix2 = HyperbolicSolver(self.source_height_m, self.box_margin_fraction, self.residual_tie_m, self.n_iterations, dimensions=2).solve(
            inputs
        )
        bad = ~usable
        out.position_m[bad], out.residual_m[bad], out.converged[bad] = fix2.position_m[bad], fix2.residual_m[bad], fix2.converged[bad]
        for name in out.diagnostics:
            if name in fix2.diagnostics:
                out.diagnostics[name][bad] = fix2.diagnostics[name][bad]
            elif name in ("height_gdop", "height_ambiguous", "other_root_residual_m"):
                out.diagnostics[name][bad] = np.nan
        return out

    def _solve_3d(self, mics: np.ndarray, rd: np.ndarray, c: np.ndarray, finite: np.ndarray) -> SolverResult:
        """x, y and height from ≥ 4 mics (see ``acoustlab.toolkit.solve3d.solve_3d``)."""
        if mics.shape[0] < 4:
            raise ValueError(f"solver.dimensions=3 needs at least 4 mics; this array has {mics.shape[0]} (use dimensions=2)")
        fix = solve_3d(mics, rd, max(self.n_iterations, 1), self.residual_tie_m)
        position = fix["position_m"]
        res = np.sqrt(fix["cost_m2"] / (mics.shape[0] - 1))
        ok = finite & np.isfinite(position).all(axis=1)
        position[~ok] = np.nan
        geometry = np.full(len(rd), np.nan)
        geometry[ok] = gdop(mics, position[ok])
        return SolverResult(
            position_m=position[:, :2],
            residual_m=np.where(ok, res, np.nan),
            converged=ok & (res < 1e3),
            diagnostics={
                "residual_s": np.where(ok, res, np.nan) / c,
                "gdop": geometry,
                "n_roots": fix["n_roots"],
                "source_height_m": position[:, 2],
                "height_gdop": np.where(ok, fix["height_gdop"], np.nan),
                "height_ambiguous": np.where(ok, fix["height_ambiguous"], np.nan),
                "other_root_residual_m": np.where(ok, fix["other_root_residual_m"], np.nan),
            },
        )
