"""The closed-form TDOA fix and its polish, compiled per event (numba): :class:`plugins.solvers.hyperbolic.HyperbolicSolver`'s maths.

:class:`~plugins.solvers.hyperbolic.HyperbolicSolver` iterates every event and root together as
numpy arrays: about 2.8 µs per 6-mic event in 2-D and 8 µs in 3-D on one core, most of it passes
over arrays of a few elements. :func:`solve_compiled` runs the same steps event by event in
compiled loops (``solver=hyperbolic_compiled``, ``solver=consistent_set_compiled``):

* 2-D (x, y at an assumed height): the closed form's two roots (p = u + v r₀, a quadratic in r₀),
  Levenberg–Marquardt on every real root with :func:`acoustlab.toolkit.tdoa.levenberg_marquardt`'s
  damping, steps and stopping rule, the root choice (residual, plausibility box, then energy
  consistency or nearness to the array), the fallback from the centroid, GDOP and conditioning;
* 3-D (x, y and height, ≥ 4 mics): :mod:`acoustlab.toolkit.solve3d`'s closed form (coplanar mics:
  the plane coordinates and both mirror images; else the quadratic), its polish, the mirror choice,
  the height's GDOP, and the 2-D fix where the 3-D one fails or is implausible.

The answers agree with the numpy solver's to within the polish's tolerance, not bit for bit: least-squares and 3 × 3
systems are solved by Gaussian elimination with partial pivoting instead of LAPACK's
pseudo-inverse and LU (the polish then converges to the same minimum), and sums run in a different
order. Written by hand: SciPy solves one problem per call
(≈ 0.5 ms), and batched numpy pays its per-call overhead on arrays of 2–12 elements.

Each event's fix runs in scalars, inlined into one loop over events: the residuals are never
stored (the polish needs only JᵀJ and Jᵀr, summed as the residuals are formed), the 3 × 3 systems
are solved in registers, and output rows are written by index. Passing an array to a compiled call
or taking a view of one costs two atomic reference counts, which took more than half of the
time of the earlier version with scratch arrays (2.5× slower in 2-D, 1.8× in 3-D; the same
answers, bit for bit). The rare paths (a pseudo-inverse where the normal equations are singular)
are calls. Compiled once per installation (``cache=True``, about 16 s on one core).
"""

from __future__ import annotations

import functools

import numba
import numpy as np

_TINY_DET = 1e-18


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _residuals_2d(px, py, mics, height, rd):
    """Σ r² of the range-difference residuals r (M−1) at (px, py, height), and JᵀJ (j00, j01, j11) and Jᵀr (g0, g1) of
    their Jacobian J (M−1, 2), each summed over the mics in order; the residuals and J themselves are never stored."""
    m = mics.shape[0]
    dz0 = height - mics[0, 2]
    dx0, dy0 = px - mics[0, 0], py - mics[0, 1]
    d0 = max(np.sqrt((dx0 * dx0 + dy0 * dy0) + dz0 * dz0), 1e-9)
    gx0, gy0 = dx0 / d0, dy0 / d0
    cost = j00 = j01 = j11 = g0 = g1 = 0.0
    for j in range(1, m):
        dx, dy, dz = px - mics[j, 0], py - mics[j, 1], height - mics[j, 2]
        d = max(np.sqrt((dx * dx + dy * dy) + dz * dz), 1e-9)
        r = (d - d0) - rd[j - 1]
        jx, jy = dx / d - gx0, dy / d - gy0
        cost += r * r
        j00 += jx * jx
        j01 += jx * jy
        j11 += jy * jy
        g0 += jx * r
        g1 += jy * r
    return cost, j00, j01, j11, g0, g1


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _lm_2d(px, py, mics, height, rd, n_iterations):
    """:func:`acoustlab.toolkit.tdoa.levenberg_marquardt` for one problem: returns (x, y, cost, last accepted step) and
    JᵀJ (j00, j01, j11) at (x, y)."""
    lam = 1e-2
    cost, j00, j01, j11, g0, g1 = _residuals_2d(px, py, mics, height, rd)
    step_norm = np.inf
    for _ in range(n_iterations):
        scale = (j00 + j11) / 2 + 1e-9
        a00, a11 = j00 + lam * scale, j11 + lam * scale
        det = a00 * a11 - j01 * j01
        if abs(det) < _TINY_DET:
            det = _TINY_DET
        sx = -(a11 * g0 - j01 * g1) / det
        sy = -(a00 * g1 - j01 * g0) / det
        nx, ny = px + sx, py + sy
        cost_new, n00, n01, n11, ng0, ng1 = _residuals_2d(nx, ny, mics, height, rd)
        better = cost_new < cost
        proposed = np.sqrt(sx * sx + sy * sy)
        if better:
            px, py, cost, step_norm = nx, ny, cost_new, proposed
            j00, j01, j11, g0, g1 = n00, n01, n11, ng0, ng1
        lam = min(max(lam * 0.3 if better else lam * 10.0, 1e-12), 1e8)
        if proposed < 1e-9 or (not better and lam >= 1e8):
            break
    return px, py, cost, step_norm, j00, j01, j11


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _gdop(j00, j01, j11):
    """:func:`acoustlab.toolkit.geometry.gdop` from HᵀH of the horizontal unknowns (the rows of H are the range
    differences' gradients u_j − u_0, the 2-D Jacobian's rows): √trace((HᵀH)⁻¹), inf where it is singular."""
    det = j00 * j11 - j01 * j01
    if not det > 1e-12:
        return np.inf
    out = np.sqrt((j00 + j11) / det)
    return out if np.isfinite(out) else np.inf


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _energy_db(px, py, height, mics, levels, b):
    """:func:`acoustlab.toolkit.tdoa.energy_residual_db` at one candidate for event b's levels (row b of ``levels``;
    NaN where a level is missing)."""
    m = mics.shape[0]
    total = 0.0
    n = 0
    for i in range(m):
        di = np.sqrt((px - mics[i, 0]) ** 2 + (py - mics[i, 1]) ** 2 + (height - mics[i, 2]) ** 2)
        ei = levels[b, i] + 20 * np.log10(max(di, 1e-3))
        for j in range(i + 1, m):
            dj = np.sqrt((px - mics[j, 0]) ** 2 + (py - mics[j, 1]) ** 2 + (height - mics[j, 2]) ** 2)
            ej = levels[b, j] + 20 * np.log10(max(dj, 1e-3))
            total += (ei - ej) ** 2
            n += 1
    return np.sqrt(total / n)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _roots_2d(mics, rd, height, pinv2):
    """The closed form's two candidate positions (p = u + v r₀, |p − m₀|² + h₀² = r₀²: the quadratic's roots, its vertex
    where the discriminant is negative): returns (is the first a real root, is the second, x₀, y₀, x₁, y₁), one root
    if both coincide."""
    m = mics.shape[0]
    h0 = height - mics[0, 2]
    u0 = u1 = v0 = v1 = 0.0
    for j in range(1, m):
        qx, qy = mics[j, 0] - mics[0, 0], mics[j, 1] - mics[0, 1]
        hj = height - mics[j, 2]
        b = ((rd[j - 1] ** 2 - (qx * qx + qy * qy)) - hj * hj) + h0 * h0
        u0 += b * pinv2[0, j - 1]
        u1 += b * pinv2[1, j - 1]
        v0 += 2 * rd[j - 1] * pinv2[0, j - 1]
        v1 += 2 * rd[j - 1] * pinv2[1, j - 1]
    a2 = (v0 * v0 + v1 * v1) - 1
    a1 = 2 * (u0 * v0 + u1 * v1)
    a0 = (u0 * u0 + u1 * u1) + h0 * h0
    disc = a1 * a1 - 4 * a2 * a0
    sqrt_disc = np.sqrt(max(disc, 0.0))
    if abs(a2) < 1e-12:
        r_plus, r_minus, vertex = -a0 / a1, np.nan, np.nan
    else:
        r_plus, r_minus, vertex = (-a1 + sqrt_disc) / (2 * a2), (-a1 - sqrt_disc) / (2 * a2), -a1 / (2 * a2)
    if disc < 0:
        r_plus, r_minus = vertex, np.nan
    x0, y0 = (u0 + v0 * r_plus) + mics[0, 0], (u1 + v1 * r_plus) + mics[0, 1]
    x1, y1 = (u0 + v0 * r_minus) + mics[0, 0], (u1 + v1 * r_minus) + mics[0, 1]
    valid_0 = np.isfinite(r_plus) and r_plus >= abs(h0) - 1e-6
    valid_1 = np.isfinite(r_minus) and r_minus >= abs(h0) - 1e-6
    if valid_0 and valid_1 and np.sqrt((x0 - x1) ** 2 + (y0 - y1) ** 2) < 1e-6:
        valid_1 = False  # two numerically identical roots count once
    return valid_0, valid_1, x0, y0, x1, y1


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _root_score(x, y, residual, best_res, mics, height, box, residual_tie, levels, b, use_levels):
    """A refined root's score, the lower the better: 10⁶ if its fit is worse than the tie of the best, 10³ if it lies
    outside the plausibility box, then its energy residual (or, without levels, 10⁻³ × its distance to the array's centroid)."""
    inside = box[0] <= x <= box[2] and box[1] <= y <= box[3]
    score = (1e6 if residual > best_res + residual_tie else 0.0) + (0.0 if inside else 1e3)
    if use_levels:
        energy = _energy_db(x, y, height, mics, levels, b)
        return score + (energy if not np.isnan(energy) else 0.0)
    return score + 1e-3 * np.sqrt((x - box[4]) ** 2 + (y - box[5]) ** 2)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _jacobian_diagnostics(j00, j01, j11):
    """Conditioning (ratio of the singular values of the (M−1, 2) Jacobian J, from the eigenvalues of the 2 × 2 JᵀJ in
    closed form) and GDOP, from JᵀJ (j00, j01, j11) at the fix."""
    half_trace = (j00 + j11) / 2
    spread = np.sqrt(((j00 - j11) / 2) ** 2 + j01 * j01)
    return np.sqrt(max(half_trace + spread, 0.0) / max(half_trace - spread, 1e-24)), _gdop(j00, j01, j11)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _fix_2d(mics, rd, height, pinv2, box, residual_tie, n_iterations, levels, b, use_levels):
    """The 2-D fix of event b (module docstring; ``levels`` row b its levels). box: low x, low y, high x, high y, the
    mics' centroid x, y. Returns x, y, residual (m), converged, conditioning, gdop, n_roots.

    Each real root is refined; the one kept has the lower :func:`_root_score` (the first where equal), as the numpy
    solver's argmin chooses. All in scalars: a view of an array per event costs two atomic reference counts, which
    cost more than the maths here."""
    m = mics.shape[0]
    valid_0, valid_1, x0, y0, x1, y1 = _roots_2d(mics, rd, height, pinv2)
    fx0 = fy0 = fx1 = fy1 = np.nan
    res_0 = res_1 = step_0 = step_1 = np.inf
    a00 = a01 = a11 = b00 = b01 = b11 = 0.0  # JᵀJ of each refined root
    if valid_0:
        fx0, fy0, cost, step_0, a00, a01, a11 = _lm_2d(x0, y0, mics, height, rd, n_iterations)
        res_0 = np.sqrt(cost / (m - 1))
    if valid_1:
        fx1, fy1, cost, step_1, b00, b01, b11 = _lm_2d(x1, y1, mics, height, rd, n_iterations)
        res_1 = np.sqrt(cost / (m - 1))
    best_res = min(res_0, res_1)
    best_score = np.inf
    if valid_0:
        best_score = min(best_score, _root_score(fx0, fy0, res_0, best_res, mics, height, box, residual_tie, levels, b, use_levels))
    if valid_1 and _root_score(fx1, fy1, res_1, best_res, mics, height, box, residual_tie, levels, b, use_levels) < best_score:
        px, py, res, step, j00, j01, j11 = fx1, fy1, res_1, step_1, b00, b01, b11
    else:
        px, py, res, step, j00, j01, j11 = fx0, fy0, res_0, step_0, a00, a01, a11
    n_roots = int(valid_0) + int(valid_1)
    if n_roots == 0:  # the closed form gave nothing: Levenberg–Marquardt from the centroid
        px, py, cost, _, j00, j01, j11 = _lm_2d(box[4], box[5], mics, height, rd, max(n_iterations, 50))
        res = np.sqrt(cost / (m - 1))
    conditioning, geometry = _jacobian_diagnostics(j00, j01, j11)
    return px, py, res, step < 1e-3 or res < 1e-6, conditioning, geometry, n_roots


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _residuals_3d(px, py, pz, mics, rd):
    """Σ r² of the 3-D range-difference residuals r (M−1) at (px, py, pz), and JᵀJ (a00, a01, a02, a11, a12, a22) and
    Jᵀr (g0, g1, g2) of their Jacobian J (M−1, 3), each summed over the mics in order (nothing is stored)."""
    m = mics.shape[0]
    dx0, dy0, dz0 = px - mics[0, 0], py - mics[0, 1], pz - mics[0, 2]
    d0 = max(np.sqrt(dx0 * dx0 + dy0 * dy0 + dz0 * dz0), 1e-9)
    gx0, gy0, gz0 = dx0 / d0, dy0 / d0, dz0 / d0
    cost = a00 = a01 = a02 = a11 = a12 = a22 = g0 = g1 = g2 = 0.0
    for j in range(1, m):
        dx, dy, dz = px - mics[j, 0], py - mics[j, 1], pz - mics[j, 2]
        d = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-9)
        r = (d - d0) - rd[j - 1]
        jx, jy, jz = dx / d - gx0, dy / d - gy0, dz / d - gz0
        cost += r * r
        g0 += jx * r
        g1 += jy * r
        g2 += jz * r
        a00 += jx * jx
        a01 += jx * jy
        a02 += jx * jz
        a11 += jy * jy
        a12 += jy * jz
        a22 += jz * jz
    return cost, a00, a01, a02, a11, a12, a22, g0, g1, g2


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _solve3(a00, a01, a02, a10, a11, a12, a20, a21, a22, b0, b1, b2):
    """x of the 3 × 3 system a x = b, by Gaussian elimination with partial pivoting (the first largest pivot), in scalars."""
    if abs(a10) > abs(a00):
        if abs(a20) > abs(a10):
            a00, a01, a02, a20, a21, a22, b0, b2 = a20, a21, a22, a00, a01, a02, b2, b0
        else:
            a00, a01, a02, a10, a11, a12, b0, b1 = a10, a11, a12, a00, a01, a02, b1, b0
    elif abs(a20) > abs(a00):
        a00, a01, a02, a20, a21, a22, b0, b2 = a20, a21, a22, a00, a01, a02, b2, b0
    f = a10 / a00
    a11, a12, b1 = a11 - f * a01, a12 - f * a02, b1 - f * b0
    f = a20 / a00
    a21, a22, b2 = a21 - f * a01, a22 - f * a02, b2 - f * b0
    if abs(a21) > abs(a11):
        a11, a12, a21, a22, b1, b2 = a21, a22, a11, a12, b2, b1
    f = a21 / a11
    a22, b2 = a22 - f * a12, b2 - f * b1
    x2 = b2 / a22
    x1 = (b1 - a12 * x2) / a11
    return ((b0 - a01 * x1) - a02 * x2) / a00, x1, x2


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _lm_3d(px, py, pz, mics, rd, n_iterations):
    """:func:`acoustlab.toolkit.solve3d.polish_3d` for one start (px, py, pz): returns the refined point, its cost (m²)
    and JᵀJ there (a00, a01, a02, a11, a12, a22)."""
    cost, a00, a01, a02, a11, a12, a22, g0, g1, g2 = _residuals_3d(px, py, pz, mics, rd)
    lam = 1e-3
    for _ in range(n_iterations):
        scale = (a00 + a11 + a22) / 3 + 1e-12
        s0, s1, s2 = _solve3(a00 + lam * scale, a01, a02, a01, a11 + lam * scale, a12, a02, a12, a22 + lam * scale, g0, g1, g2)
        nx, ny, nz = px - s0, py - s1, pz - s2
        new = _residuals_3d(nx, ny, nz, mics, rd)
        better = new[0] < cost
        if better:
            px, py, pz = nx, ny, nz
            cost, a00, a01, a02, a11, a12, a22, g0, g1, g2 = new
        lam = min(max(lam * 0.3 if better else lam * 10.0, 1e-12), 1e8)
        if np.sqrt(s0 * s0 + s1 * s1 + s2 * s2) < 1e-9 or (not better and lam >= 1e8):
            break
    return px, py, pz, cost, a00, a01, a02, a11, a12, a22


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _det3(a00, a01, a02, a10, a11, a12, a20, a21, a22):
    return a00 * (a11 * a22 - a12 * a21) - a01 * (a10 * a22 - a12 * a20) + a02 * (a10 * a21 - a11 * a20)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _closed_form_rhs(mics, rd, j):
    """The 3-D closed forms' right side for mic j ≥ 1: d_j² − |m_j − m_0|² (d_j its range difference to mic 0, m)."""
    return rd[j - 1] ** 2 - ((mics[j, 0] - mics[0, 0]) ** 2 + (mics[j, 1] - mics[0, 1]) ** 2 + (mics[j, 2] - mics[0, 2]) ** 2)


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _from_mic0(d0, d1, d2, mics):
    """Mic 0's position plus the offset (d0, d1, d2): a closed-form candidate position (x, y, z), m."""
    return d0 + mics[0, 0], d1 + mics[0, 1], d2 + mics[0, 2]


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _mirror_point(s0, s1, w, frame, mics):
    """The position (x, y, z) at plane coordinates (s0, s1) and signed distance w off the mics' plane, m."""
    return _from_mic0(s0 * frame[0, 0] + s1 * frame[1, 0] + w * frame[2, 0], s0 * frame[0, 1] + s1 * frame[1, 1] + w * frame[2, 1],
                      s0 * frame[0, 2] + s1 * frame[1, 2] + w * frame[2, 2], mics)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _coplanar_pinv(mics, rd, local):
    """:func:`_coplanar_roots`' least squares where its normal equations are (near-)singular: the pseudo-inverse's
    minimum-norm solution, as numpy (a call, not inlined: it is rare, and allocates)."""
    m = mics.shape[0]
    design = np.empty((m - 1, 3))
    rhs = np.empty(m - 1)
    for j in range(1, m):
        design[j - 1, 0], design[j - 1, 1], design[j - 1, 2] = -2 * local[j - 1, 0], -2 * local[j - 1, 1], -2 * rd[j - 1]
        rhs[j - 1] = _closed_form_rhs(mics, rd, j)
    solution = np.linalg.pinv(design) @ rhs
    return solution[0], solution[1], solution[2]


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _coplanar_roots(mics, rd, frame, local):
    """Coplanar mics: least squares in the plane coordinates and r₀ (rows −2 local_j, −2 d_j; right side d_j² − |q_j|²),
    then both mirror images ±w off the plane: returns (x₀, y₀, z₀, x₁, y₁, z₁), NaN without a solution with r₀ ≥ 0."""
    m = mics.shape[0]
    a00 = a01 = a02 = a11 = a12 = a22 = g0 = g1 = g2 = 0.0
    for j in range(1, m):
        w0, w1, w2 = -2 * local[j - 1, 0], -2 * local[j - 1, 1], -2 * rd[j - 1]
        rhs = _closed_form_rhs(mics, rd, j)
        g0 += w0 * rhs
        a00 += w0 * w0
        a01 += w0 * w1
        a02 += w0 * w2
        g1 += w1 * rhs
        a11 += w1 * w1
        a12 += w1 * w2
        g2 += w2 * rhs
        a22 += w2 * w2
    if _det3(a00, a01, a02, a01, a11, a12, a02, a12, a22) > 1e-12 * (a00 + a11 + a22) ** 3:  # normal equations, well conditioned
        s0, s1, r0 = _solve3(a00, a01, a02, a01, a11, a12, a02, a12, a22, g0, g1, g2)
    else:  # (near-)rank-deficient, e.g. equal arrival times
        s0, s1, r0 = _coplanar_pinv(mics, rd, local)
    if not (np.isfinite(s0) and np.isfinite(s1) and np.isfinite(r0) and r0 >= 0):
        return np.nan, np.nan, np.nan, np.nan, np.nan, np.nan
    w = np.sqrt(max(r0 * r0 - s0 * s0 - s1 * s1, 0.0))
    x0, y0, z0 = _mirror_point(s0, s1, w, frame, mics)
    x1, y1, z1 = _mirror_point(s0, s1, -w, frame, mics)
    return x0, y0, z0, x1, y1, z1


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _quadratic_roots_3d(mics, rd, pinv3):
    """Mics off a plane: p = u + v r₀ and |p − m₀| = r₀, a quadratic in r₀; its roots ≥ 0 (the vertex twice where the
    discriminant is negative): returns (x₀, y₀, z₀, x₁, y₁, z₁), NaN for a root < 0."""
    m = mics.shape[0]
    u0 = u1 = u2 = v0 = v1 = v2 = 0.0
    for j in range(1, m):
        b = _closed_form_rhs(mics, rd, j)
        u0 += b * pinv3[0, j - 1]
        v0 += 2 * rd[j - 1] * pinv3[0, j - 1]
        u1 += b * pinv3[1, j - 1]
        v1 += 2 * rd[j - 1] * pinv3[1, j - 1]
        u2 += b * pinv3[2, j - 1]
        v2 += 2 * rd[j - 1] * pinv3[2, j - 1]
    a2 = (v0 * v0 + v1 * v1 + v2 * v2) - 1
    a1 = 2 * (u0 * v0 + u1 * v1 + u2 * v2)
    a0 = u0 * u0 + u1 * u1 + u2 * u2
    disc = a1 * a1 - 4 * a2 * a0
    root = np.sqrt(max(disc, 0.0))
    r_0 = (-a1 / (2 * a2)) if disc < 0 else (-a1 + root) / (2 * a2)
    r_1 = (-a1 / (2 * a2)) if disc < 0 else (-a1 - root) / (2 * a2)
    x0 = y0 = z0 = x1 = y1 = z1 = np.nan
    if np.isfinite(r_0) and r_0 >= 0:
        x0, y0, z0 = _from_mic0(u0 + v0 * r_0, u1 + v1 * r_0, u2 + v2 * r_0, mics)
    if np.isfinite(r_1) and r_1 >= 0:
        x1, y1, z1 = _from_mic0(u0 + v0 * r_1, u1 + v1 * r_1, u2 + v2 * r_1, mics)
    return x0, y0, z0, x1, y1, z1


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _height_gdop(a00, a01, a02, a11, a12, a22):
    """√((JᵀJ)⁻¹)₂₂ for the symmetric 3 × 3 normal matrix JᵀJ: the inverse where λ_min > 10⁻¹² λ_max (then it is the
    pseudo-inverse), else numpy's hermitian pseudo-inverse (a source in the mics' plane, where the height is
    unobservable to first order)."""
    det = _det3(a00, a01, a02, a01, a11, a12, a02, a12, a22)
    if det > 1e-12 * (a00 + a11 + a22) ** 3:
        return np.sqrt(max((a00 * a11 - a01 * a01) / det, 0.0))
    if not np.isfinite(det):
        return np.nan
    return _height_gdop_pinv(a00, a01, a02, a11, a12, a22)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _height_gdop_pinv(a00, a01, a02, a11, a12, a22):
    """:func:`_height_gdop` where JᵀJ is (near-)singular: numpy's hermitian pseudo-inverse (a call, not inlined: it is rare)."""
    a = np.empty((3, 3))
    a[0, 0], a[0, 1], a[0, 2], a[1, 0], a[1, 1], a[1, 2], a[2, 0], a[2, 1], a[2, 2] = a00, a01, a02, a01, a11, a12, a02, a12, a22
    w, vec = np.linalg.eigh(a)
    cutoff = 1e-15 * max(abs(w[0]), abs(w[1]), abs(w[2]))
    cov = 0.0
    for k in range(3):
        if abs(w[k]) > cutoff:
            cov += vec[2, k] * vec[2, k] / w[k]
    return np.sqrt(max(cov, 0.0))


@numba.njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _fix_3d(mics, rd, coplanar, frame, local, pinv3, residual_tie, n_iterations):
    """The 3-D fix of one event: returns x, y, z, cost (m², inf if none), height_ambiguous, height_gdop, n_roots, gdop.
    All in scalars, as :func:`_fix_2d`."""
    m = mics.shape[0]
    if coplanar:
        x0, y0, z0, x1, y1, z1 = _coplanar_roots(mics, rd, frame, local)
    else:
        x0, y0, z0, x1, y1, z1 = _quadratic_roots_3d(mics, rd, pinv3)
    valid_0 = np.isfinite(x0) and np.isfinite(y0) and np.isfinite(z0)
    valid_1 = np.isfinite(x1) and np.isfinite(y1) and np.isfinite(z1)
    cost_0 = cost_1 = np.inf
    p00 = p01 = p02 = p11 = p12 = p22 = q00 = q01 = q02 = q11 = q12 = q22 = 0.0  # JᵀJ at each refined root
    if valid_0:
        x0, y0, z0, cost_0, p00, p01, p02, p11, p12, p22 = _lm_3d(x0, y0, z0, mics, rd, n_iterations)
    if valid_1:
        x1, y1, z1, cost_1, q00, q01, q02, q11, q12, q22 = _lm_3d(x1, y1, z1, mics, rd, n_iterations)
    # above ground where possible; among fits within the tie of the best, the upper one (the first where equal)
    above_0, above_1 = valid_0 and z0 >= 0, valid_1 and z1 >= 0
    usable_0, usable_1 = (above_0, above_1) if (above_0 or above_1) else (valid_0, valid_1)
    fit_0, fit_1 = np.sqrt(cost_0 / (m - 1)), np.sqrt(cost_1 / (m - 1))
    best_fit = min(fit_0 if usable_0 else np.inf, fit_1 if usable_1 else np.inf)
    tie_0, tie_1 = usable_0 and fit_0 <= best_fit + residual_tie, usable_1 and fit_1 <= best_fit + residual_tie
    if tie_1 and (not tie_0 or z1 > z0):
        px, py, pz, cost, a00, a01, a02, a11, a12, a22 = x1, y1, z1, cost_1, q00, q01, q02, q11, q12, q22
    else:
        px, py, pz, cost, a00, a01, a02, a11, a12, a22 = x0, y0, z0, cost_0, p00, p01, p02, p11, p12, p22
    two_above = tie_0 and above_0 and tie_1 and above_1
    ambiguous = 1.0 if (two_above and abs(z0 - z1) > 2 * residual_tie) else 0.0
    n_roots = int(valid_0) + int(valid_1)
    height_gdop = geometry = np.nan
    if n_roots:
        if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):  # else JᵀJ at the fix is the polish's, as computed there
            _, a00, a01, a02, a11, a12, a22, _, _, _ = _residuals_3d(px if np.isfinite(px) else 0.0, py if np.isfinite(py) else 0.0,
                                                                     pz if np.isfinite(pz) else 0.0, mics, rd)
        geometry = _gdop(a00, a01, a11)  # the x, y columns are the horizontal GDOP's gradients at this height
        height_gdop = _height_gdop(a00, a01, a02, a11, a12, a22)
    return px, py, pz, cost, ambiguous, height_gdop, n_roots, geometry


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _solve_batch(mics, tdoa, speed, height, levels, use_levels, dims, fallback_2d, pinv2, box, box_wide, coplanar, frame, local, pinv3,
                 residual_tie, n_iterations, out):
    """Every event's fix into out (B, 12): x, y, residual (m), converged, conditioning, gdop, n_roots, source height,
    height_gdop, height_ambiguous, dimensions_used and the residual in s, as :class:`HyperbolicSolver` reports them."""
    bsz, m = tdoa.shape
    rd = np.empty(m - 1)
    for b in range(bsz):  # rows of out by index: a view per event would cost atomic reference counts
        finite = np.isfinite(speed[b])
        for j in range(m):
            finite = finite and np.isfinite(tdoa[b, j])
        for j in range(1, m):
            rd[j - 1] = speed[b] * (tdoa[b, j] - tdoa[b, 0]) if finite else 0.0
        for n in range(12):
            out[b, n] = np.nan
        if dims == 3:
            x, y, z, cost, ambiguous, height_gdop, n_roots, geometry = _fix_3d(mics, rd, coplanar, frame, local, pinv3, residual_tie,
                                                                               max(n_iterations, 1))
            res = np.sqrt(cost / (m - 1))
            ok = finite and np.isfinite(x) and np.isfinite(y) and np.isfinite(z)
            usable = ok and box_wide[0] <= x <= box_wide[2] and box_wide[1] <= y <= box_wide[3] and z >= 0
            if usable or not fallback_2d:
                if ok:
                    out[b, 0], out[b, 1], out[b, 2] = x, y, res
                    out[b, 5] = geometry
                    out[b, 7], out[b, 8], out[b, 9], out[b, 10] = z, height_gdop, ambiguous, 3.0
                    out[b, 11] = res / speed[b]
                out[b, 3] = ok and res < 1e3
                out[b, 6] = n_roots
                continue
        # 2-D at the assumed height (dims 2, or the 3-D fix failed or is implausible)
        px, py, res, converged, conditioning, geometry, n_roots = _fix_2d(mics, rd, height, pinv2, box, residual_tie, n_iterations, levels, b,
                                                                        use_levels)
        if finite:
            out[b, 0], out[b, 1], out[b, 2], out[b, 3], out[b, 4], out[b, 5] = px, py, res, converged, conditioning, geometry
            out[b, 11] = res / speed[b]
        else:
            out[b, 3] = 0.0
        out[b, 6], out[b, 7], out[b, 10] = n_roots, height, 2.0


@functools.lru_cache(maxsize=64)
def _geometry(mics_bytes: bytes, n_mics: int, dimensions: int, box_margin_fraction: float) -> tuple:
    """What the kernels need of an array's geometry, computed once per array (a season solves it batch after batch):
    the 2-D closed form's pseudo-inverse, the plausibility box and the mics' centroid, the wider box of the 3-D fallback,
    and :func:`plane_geometry` (3-D only)."""
    from acoustlab.toolkit.geometry import bounding_box

    mics = np.frombuffer(mics_bytes, dtype=np.float64).reshape(n_mics, 3)
    pinv2 = np.ascontiguousarray(np.linalg.pinv(-2 * (mics[1:, :2] - mics[0, :2])))
    box = np.concatenate([*bounding_box(mics, box_margin_fraction), mics[:, :2].mean(axis=0)])
    box_wide = np.concatenate(bounding_box(mics, 1.0))
    if dimensions == 3:
        coplanar, frame, local, pinv3 = plane_geometry(mics)
    else:
        coplanar, frame, local, pinv3 = False, np.eye(3), np.zeros((n_mics - 1, 3)), np.zeros((3, n_mics - 1))
    for array in (pinv2, box, box_wide, frame, local, pinv3):
        array.setflags(write=False)
    return pinv2, box, box_wide, bool(coplanar), frame, local, pinv3


def plane_geometry(mics: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray]:
    """What the 3-D closed form needs of the mics (M, 3): coplanar?, the plane frame (3, 3), the other mics in its
    coordinates (M−1, 3) and the pseudo-inverse (3, M−1) of −2 (m_j − m_0) for mics off a plane (as :mod:`acoustlab.toolkit.solve3d`)."""
    from acoustlab.toolkit.solve3d import _plane_frame

    frame, coplanar = _plane_frame(mics)
    q = mics[1:] - mics[0]
    pinv3 = np.zeros((3, len(q))) if coplanar else np.linalg.pinv(-2 * q)
    return coplanar, np.ascontiguousarray(frame), np.ascontiguousarray(q @ frame.T), np.ascontiguousarray(pinv3)


#: Columns of :func:`solve_compiled`'s diagnostics, in the kernel's order after x, y, residual and converged.
_COLUMNS = ("conditioning", "gdop", "n_roots", "source_height_m", "height_gdop", "height_ambiguous", "dimensions_used", "residual_s")


def solve_compiled(mics: np.ndarray, tdoa: np.ndarray, speed: np.ndarray, height: float, levels_db: np.ndarray | None, *, dimensions: int,
                   fallback_2d: bool, box_margin_fraction: float, residual_tie_m: float, n_iterations: int) -> dict[str, np.ndarray]:
    """Fixes of every event, as :meth:`plugins.solvers.hyperbolic.HyperbolicSolver.solve` computes them (module docstring).

    Parameters
    ----------
    mics : numpy.ndarray
        (M, 3) mic positions, m.
    tdoa : numpy.ndarray
        (B, M) arrival times relative to any reference, s (NaN: the event has no fix).
    speed : numpy.ndarray
        (B,) speed of sound, m/s.
    height : float
        Assumed source height for the 2-D fix, m.
    levels_db : numpy.ndarray or None
        (B, M) received levels for the energy-consistency root choice, dB.
    dimensions, fallback_2d, box_margin_fraction, residual_tie_m, n_iterations
        As :class:`~plugins.solvers.hyperbolic.HyperbolicSolver`'s parameters.

    Returns
    -------
    dict
        ``position_m`` (B, 2), ``residual_m`` (B,), ``converged`` (B,) bool and the diagnostics
        ``conditioning``, ``gdop``, ``n_roots``, ``source_height_m``, ``height_gdop``,
        ``height_ambiguous``, ``dimensions_used``, ``residual_s`` (B,) (NaN where a mode does not report one).
    """
    mics = np.ascontiguousarray(mics, dtype=np.float64)
    tdoa = np.ascontiguousarray(tdoa, dtype=np.float64)
    speed = np.ascontiguousarray(np.broadcast_to(speed, (len(tdoa),)), dtype=np.float64)
    pinv2, box, box_wide, coplanar, frame, local, pinv3 = _geometry(mics.tobytes(), len(mics), int(dimensions), float(box_margin_fraction))
    use_levels = levels_db is not None
    levels = np.ascontiguousarray(levels_db if use_levels else np.zeros((len(tdoa), len(mics))), dtype=np.float64)
    out = np.empty((len(tdoa), 12))
    _solve_batch(mics, tdoa, speed, float(height), levels, use_levels, int(dimensions), bool(fallback_2d), pinv2, box, box_wide,
                 bool(coplanar), frame, local, pinv3, float(residual_tie_m), int(n_iterations), out)
    return {"position_m": out[:, :2].copy(), "residual_m": out[:, 2].copy(), "converged": out[:, 3] == 1.0,
            **{name: out[:, 4 + n].copy() for n, name in enumerate(_COLUMNS)}}
