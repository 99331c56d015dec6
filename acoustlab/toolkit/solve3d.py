"""3-D TDOA fixes (x, y and the source height) from ≥ 4 mics: closed form, polish, mirror choice.

With mic 0 as origin, q_j the other mics (3-D), range differences d_j = c (t_j − t_0) and
r_0 = |p|, squaring r_j = r_0 + d_j gives −2 q_j·p − 2 d_j r_0 = d_j² − |q_j|², linear in
(p, r_0).

* **Coplanar mics** (every ARU at about the same height): in the mics' plane coordinates
  (s₁, s₂, w) the q_j have no w, so the equations are linear in (s₁, s₂, r_0) (≥ 3 equations:
  ≥ 4 mics) and w = ±√(r_0² − s₁² − s₂²). The two mirror images fit the TDOAs equally well; the
  ground (z ≥ 0) removes the one below it, and where both are above ground the fix is flagged
  ``height_ambiguous`` and the upper one is reported. The height's precision is poor near the
  mics' plane (w → 0): ``height_gdop`` says how poor.
* **Mics off a plane**: p = u + v r_0 from the least-squares solution, and |p| = r_0 is a quadratic
  in r_0 (up to two roots, as in 2-D).

Each candidate is polished by Levenberg–Marquardt on all range differences (3 unknowns), batched.
Hand-written for the same reason as ``acoustlab.toolkit.tdoa``: SciPy solves one problem per call.
"""

from __future__ import annotations

import numpy as np


def range_residuals_3d(p: np.ndarray, mics: np.ndarray, rd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (N, M−1) of the range differences at positions p (N, 3) and their Jacobian (N, M−1, 3)."""
    diff = p[:, None, :] - mics[None]
    dist = np.maximum(np.sqrt((diff**2).sum(-1)), 1e-9)
    grad = diff / dist[..., None]
    return (dist[:, 1:] - dist[:, :1]) - rd, grad[:, 1:] - grad[:, :1]


def polish_3d(p0: np.ndarray, mics: np.ndarray, rd: np.ndarray, n_iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg–Marquardt on the range differences from starts p0 (N, 3); returns positions and costs (m²)."""
    p = np.array(p0, dtype=float)
    r, jac = range_residuals_3d(p, mics, rd)
    cost = (r**2).sum(-1)
    lam = np.full(len(p), 1e-3)
    act = np.flatnonzero(np.isfinite(p).all(-1))
    eye = np.eye(3)
    for _ in range(n_iterations):
        if act.size == 0:
            break
        ja, ra = jac[act], r[act]
        jtj = np.einsum("bki,bkj->bij", ja, ja)
        scale = np.trace(jtj, axis1=1, axis2=2)[:, None, None] / 3 + 1e-12
        step = -np.linalg.solve(jtj + lam[act, None, None] * scale * eye, np.einsum("bki,bk->bi", ja, ra)[..., None])[..., 0]
        p_new = p[act] + step
        r_new, jac_new = range_residuals_3d(p_new, mics, rd[act])
        cost_new = (r_new**2).sum(-1)
        better = cost_new < cost[act]
        won = act[better]
        p[won], r[won], jac[won], cost[won] = p_new[better], r_new[better], jac_new[better], cost_new[better]
        lam[act] = np.clip(np.where(better, lam[act] * 0.3, lam[act] * 10.0), 1e-12, 1e8)
        done = (np.sqrt((step**2).sum(-1)) < 1e-9) | (~better & (lam[act] >= 1e8))
        act = act[~done]
    return p, cost


def _plane_frame(mics: np.ndarray) -> tuple[np.ndarray, bool]:
    """Orthonormal rows (e₁, e₂, n) with n the mics' best-fit plane normal (pointing up), and whether they are coplanar."""
    centred = mics - mics.mean(axis=0)
    _, s, vt = np.linalg.svd(centred)
    normal = vt[2] if vt[2, 2] >= 0 else -vt[2]
    coplanar = s[2] <= 1e-6 * max(s[0], 1e-12)
    return np.vstack([vt[0], np.cross(normal, vt[0]), normal]), bool(coplanar)


def closed_form_3d(mics: np.ndarray, rd: np.ndarray) -> np.ndarray:
    """Up to two candidate 3-D positions (B, 2, 3) for range differences rd (B, M−1) to mic 0 (NaN: no root)."""
    q = mics[1:] - mics[0]
    b = rd**2 - (q**2).sum(-1)  # (B, M-1)
    frame, coplanar = _plane_frame(mics)
    if coplanar:
        local = q @ frame.T  # (M-1, 3); the third column is ≈ 0
        out = np.full((len(rd), 2, 3), np.nan)
        a = np.empty((len(rd), len(q), 3))  # unknowns s1, s2, r0; the r0 column differs per event
        a[:, :, :2] = -2 * local[:, :2]
        a[:, :, 2] = -2 * rd
        sol = np.einsum("bij,bj->bi", np.linalg.pinv(a), b)  # (B, 3): s1, s2, r0
        w2 = sol[:, 2] ** 2 - sol[:, 0] ** 2 - sol[:, 1] ** 2
        w = np.sqrt(np.maximum(w2, 0.0))
        ok = np.isfinite(sol).all(-1) & (sol[:, 2] >= 0)
        for k, sign in enumerate((1.0, -1.0)):
            local_p = np.column_stack([sol[:, 0], sol[:, 1], sign * w])
            out[:, k] = np.where(ok[:, None], np.einsum("bk,kj->bj", local_p, frame) + mics[0], np.nan)
        return out
    pinv = np.linalg.pinv(-2 * q)  # (3, M-1)
    # einsum, not @: BLAS rounds a row differently by how many rows come with it, and a fix must not depend on its batch
    u = np.einsum("bk,jk->bj", b, pinv)
    v = np.einsum("bk,jk->bj", 2 * rd, pinv)
    a2 = (v**2).sum(-1) - 1
    a1 = 2 * (u * v).sum(-1)
    a0 = (u**2).sum(-1)
    disc = a1**2 - 4 * a2 * a0
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.sqrt(np.maximum(disc, 0.0))
        r0 = np.stack([(-a1 + root) / (2 * a2), (-a1 - root) / (2 * a2)], axis=1)
    r0 = np.where(disc[:, None] < 0, (-a1 / (2 * a2))[:, None], r0)
    r0 = np.where(np.isfinite(r0) & (r0 >= 0), r0, np.nan)
    return u[:, None, :] + v[:, None, :] * r0[..., None] + mics[0]


#: A misfit below this (m) is numerical precision: roots fitting that well tie whatever their ratio.
NUMERICAL_FIT_M = 1e-6


def solve_3d(mics: np.ndarray, rd: np.ndarray, n_iterations: int = 30, residual_tie_m: float = 0.05) -> dict[str, np.ndarray]:
    """3-D fixes for range differences rd (B, M−1) to mic 0 with mics (M ≥ 4, 3); see the module docstring.

    Returns
    -------
    dict
        ``position_m`` (B, 3); ``cost_m2`` (B,) sum of squared residuals; ``height_ambiguous`` (B,) 1
        where both mirror images are above ground and fit equally well; ``other_root_residual_m`` (B,)
        the RMS residual of the root not chosen (NaN with one root); ``height_gdop`` (B,) the
        factor from a range-difference standard deviation (m) to the height's (m); ``n_roots`` (B,).
    """
    if mics.shape[0] < 4:
        raise ValueError(f"a 3-D fix needs at least 4 mics; got {mics.shape[0]}")
    bsz = len(rd)
    cand = closed_form_3d(mics, rd)  # (B, 2, 3)
    valid = np.isfinite(cand).all(-1)
    refined = np.full(cand.shape, np.nan)
    cost = np.full(valid.shape, np.inf)
    b_idx, k_idx = np.nonzero(valid)
    refined[b_idx, k_idx], cost[b_idx, k_idx] = polish_3d(cand[b_idx, k_idx], mics, rd[b_idx], n_iterations)
    above = valid & (refined[..., 2] >= 0)
    fit = np.sqrt(cost / (mics.shape[0] - 1))
    usable = np.where(above.any(axis=1, keepdims=True), above, valid)
    best_fit = np.where(usable, fit, np.inf).min(axis=1, keepdims=True)
    # Two roots tie (a coplanar array's mirror images) when they fit alike: within residual_tie_m and within the better
    # one's own misfit, i.e. the measurement noise. A root that fits to numerical precision is never beaten by one 3 cm off.
    tie = usable & (fit <= best_fit + np.minimum(residual_tie_m, np.maximum(best_fit, NUMERICAL_FIT_M)))
    # among equally good fits take the upper one (the mirror of a coplanar array is below it)
    choice = np.argmax(np.where(tie, refined[..., 2], -np.inf), axis=1)
    rows = np.arange(bsz)
    position = refined[rows, choice]
    ambiguous = (tie & above).sum(axis=1) >= 2
    ambiguous &= np.abs(refined[:, 0, 2] - refined[:, 1, 2]) > 2 * residual_tie_m
    _, jac = range_residuals_3d(np.nan_to_num(position), mics, rd)
    jtj = np.einsum("bki,bkj->bij", jac, jac)
    with np.errstate(divide="ignore", invalid="ignore"):
        cov = np.linalg.pinv(jtj, hermitian=True)
    height_gdop = np.sqrt(np.maximum(cov[:, 2, 2], 0.0))
    none = ~valid.any(axis=1)
    height_gdop[none] = np.nan
    return {
        "position_m": position,
        "cost_m2": cost[rows, choice],
        "height_ambiguous": ambiguous.astype(float),
        "other_root_residual_m": np.where(valid[rows, 1 - choice], fit[rows, 1 - choice], np.nan),
        "height_gdop": height_gdop,
        "n_roots": valid.sum(axis=1).astype(float),
    }
