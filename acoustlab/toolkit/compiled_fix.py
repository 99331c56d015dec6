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
"""

from __future__ import annotations

import functools

import numba
import numpy as np

_TINY_DET = 1e-18


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _residuals_2d(px, py, mics, height, rd, r, jac):
    """Range-difference residuals r (M−1) and their Jacobian jac (M−1, 2) at (px, py, height); returns Σ r²."""
    m = mics.shape[0]
    dz0 = height - mics[0, 2]
    dx0, dy0 = px - mics[0, 0], py - mics[0, 1]
    d0 = max(np.sqrt((dx0 * dx0 + dy0 * dy0) + dz0 * dz0), 1e-9)
    gx0, gy0 = dx0 / d0, dy0 / d0
    cost = 0.0
    for j in range(1, m):
        dx, dy, dz = px - mics[j, 0], py - mics[j, 1], height - mics[j, 2]
        d = max(np.sqrt((dx * dx + dy * dy) + dz * dz), 1e-9)
        r[j - 1] = (d - d0) - rd[j - 1]
        jac[j - 1, 0] = dx / d - gx0
        jac[j - 1, 1] = dy / d - gy0
        cost += r[j - 1] * r[j - 1]
    return cost


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _lm_2d(px, py, mics, height, rd, n_iterations, r, jac, r_new, jac_new):
    """:func:`acoustlab.toolkit.tdoa.levenberg_marquardt` for one problem: returns (x, y, cost, last accepted step)."""
    m = mics.shape[0]
    lam = 1e-2
    cost = _residuals_2d(px, py, mics, height, rd, r, jac)
    step_norm = np.inf
    for _ in range(n_iterations):
        j00 = j01 = j11 = g0 = g1 = 0.0
        for k in range(m - 1):
            j00 += jac[k, 0] * jac[k, 0]
            j01 += jac[k, 0] * jac[k, 1]
            j11 += jac[k, 1] * jac[k, 1]
            g0 += jac[k, 0] * r[k]
            g1 += jac[k, 1] * r[k]
        scale = (j00 + j11) / 2 + 1e-9
        a00, a11 = j00 + lam * scale, j11 + lam * scale
        det = a00 * a11 - j01 * j01
        if abs(det) < _TINY_DET:
            det = _TINY_DET
        sx = -(a11 * g0 - j01 * g1) / det
        sy = -(a00 * g1 - j01 * g0) / det
        nx, ny = px + sx, py + sy
        cost_new = _residuals_2d(nx, ny, mics, height, rd, r_new, jac_new)
        better = cost_new < cost
        proposed = np.sqrt(sx * sx + sy * sy)
        if better:
            px, py, cost, step_norm = nx, ny, cost_new, proposed
            for k in range(m - 1):
                r[k] = r_new[k]
                jac[k, 0], jac[k, 1] = jac_new[k, 0], jac_new[k, 1]
        lam = min(max(lam * 0.3 if better else lam * 10.0, 1e-12), 1e8)
        if proposed < 1e-9 or (not better and lam >= 1e8):
            break
    return px, py, cost, step_norm


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _gdop(j00, j01, j11):
    """:func:`acoustlab.toolkit.geometry.gdop` from HᵀH of the horizontal unknowns (the rows of H are the range
    differences' gradients u_j − u_0, the 2-D Jacobian's rows): √trace((HᵀH)⁻¹), inf where it is singular."""
    det = j00 * j11 - j01 * j01
    if not det > 1e-12:
        return np.inf
    out = np.sqrt((j00 + j11) / det)
    return out if np.isfinite(out) else np.inf


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _energy_db(px, py, height, mics, levels):
    """:func:`acoustlab.toolkit.tdoa.energy_residual_db` at one candidate (NaN where a level is missing)."""
    m = mics.shape[0]
    total = 0.0
    n = 0
    for i in range(m):
        di = np.sqrt((px - mics[i, 0]) ** 2 + (py - mics[i, 1]) ** 2 + (height - mics[i, 2]) ** 2)
        ei = levels[i] + 20 * np.log10(max(di, 1e-3))
        for j in range(i + 1, m):
            dj = np.sqrt((px - mics[j, 0]) ** 2 + (py - mics[j, 1]) ** 2 + (height - mics[j, 2]) ** 2)
            ej = levels[j] + 20 * np.log10(max(dj, 1e-3))
            total += (ei - ej) ** 2
            n += 1
    return np.sqrt(total / n)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _roots_2d(mics, rd, height, pinv2, cx, cy):
    """The closed form's candidate positions into cx, cy (2,); returns whether each is a real root (p = u + v r₀,
    |p − m₀|² + h₀² = r₀²: the quadratic's roots, its vertex where the discriminant is negative, one root if both coincide)."""
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
    cx[0], cy[0] = (u0 + v0 * r_plus) + mics[0, 0], (u1 + v1 * r_plus) + mics[0, 1]
    cx[1], cy[1] = (u0 + v0 * r_minus) + mics[0, 0], (u1 + v1 * r_minus) + mics[0, 1]
    valid_0 = np.isfinite(r_plus) and r_plus >= abs(h0) - 1e-6
    valid_1 = np.isfinite(r_minus) and r_minus >= abs(h0) - 1e-6
    if valid_0 and valid_1 and np.sqrt((cx[0] - cx[1]) ** 2 + (cy[0] - cy[1]) ** 2) < 1e-6:
        valid_1 = False  # two numerically identical roots count once
    return valid_0, valid_1


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _root_choice(fx, fy, residual, valid, mics, height, box, residual_tie, levels, use_levels):
    """Index of the refined root to keep: a fit within the tie of the best, inside the plausibility box, then the
    smaller energy residual (or, without levels, nearer the array's centroid); 0 when neither root is real."""
    best_res = min(residual[0], residual[1])
    choice = 0
    best_score = np.inf
    for n in range(2):
        if not valid[n]:
            continue
        inside = box[0] <= fx[n] <= box[2] and box[1] <= fy[n] <= box[3]
        score = (1e6 if residual[n] > best_res + residual_tie else 0.0) + (0.0 if inside else 1e3)
        if use_levels:
            energy = _energy_db(fx[n], fy[n], height, mics, levels)
            score += energy if not np.isnan(energy) else 0.0
        else:
            score += 1e-3 * np.sqrt((fx[n] - box[4]) ** 2 + (fy[n] - box[5]) ** 2)
        if score < best_score:
            best_score, choice = score, n
    return choice


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _jacobian_diagnostics(jac, m1):
    """Conditioning (ratio of the singular values of the (M−1, 2) Jacobian, from the eigenvalues of the 2 × 2 JᵀJ in
    closed form) and GDOP at the point where ``jac`` was evaluated."""
    j00 = j01 = j11 = 0.0
    for k in range(m1):
        j00 += jac[k, 0] * jac[k, 0]
        j01 += jac[k, 0] * jac[k, 1]
        j11 += jac[k, 1] * jac[k, 1]
    half_trace = (j00 + j11) / 2
    spread = np.sqrt(((j00 - j11) / 2) ** 2 + j01 * j01)
    return np.sqrt(max(half_trace + spread, 0.0) / max(half_trace - spread, 1e-24)), _gdop(j00, j01, j11)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fix_2d(mics, rd, height, pinv2, box, residual_tie, n_iterations, levels, use_levels, work, buf, out):
    """The 2-D fix of one event (module docstring). box: low x, low y, high x, high y, the mics' centroid x, y;
    buf (6, 2) scratch; out: x, y, residual (m), converged, conditioning, gdop, n_roots."""
    m = mics.shape[0]
    r, jac, r_new, jac_new = work  # r (2, M−1), jac (2, M−1, 2): each root's residuals and Jacobian at its refined point
    cx, cy, fx, fy, residual, step = buf[0], buf[1], buf[2], buf[3], buf[4], buf[5]
    valid = _roots_2d(mics, rd, height, pinv2, cx, cy)
    for n in range(2):
        fx[n] = fy[n] = np.nan
        residual[n] = step[n] = np.inf
        if valid[n]:
            fx[n], fy[n], cost, step[n] = _lm_2d(cx[n], cy[n], mics, height, rd, n_iterations, r[n], jac[n], r_new, jac_new)
            residual[n] = np.sqrt(cost / (m - 1))
    choice = _root_choice(fx, fy, residual, valid, mics, height, box, residual_tie, levels, use_levels)
    px, py, res = fx[choice], fy[choice], residual[choice]
    n_roots = int(valid[0]) + int(valid[1])
    if n_roots == 0:  # the closed form gave nothing: Levenberg–Marquardt from the centroid
        px, py, cost, _ = _lm_2d(box[4], box[5], mics, height, rd, max(n_iterations, 50), r[0], jac[0], r_new, jac_new)
        res = np.sqrt(cost / (m - 1))
    out[0], out[1], out[2], out[3] = px, py, res, step[choice] < 1e-3 or res < 1e-6
    out[4], out[5] = _jacobian_diagnostics(jac[choice], m - 1)
    out[6] = n_roots


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _residuals_3d(px, py, pz, mics, rd, r, jac):
    """3-D residuals r (M−1), Jacobian jac (M−1, 3); returns Σ r²."""
    m = mics.shape[0]
    dx0, dy0, dz0 = px - mics[0, 0], py - mics[0, 1], pz - mics[0, 2]
    d0 = max(np.sqrt(dx0 * dx0 + dy0 * dy0 + dz0 * dz0), 1e-9)
    cost = 0.0
    for j in range(1, m):
        dx, dy, dz = px - mics[j, 0], py - mics[j, 1], pz - mics[j, 2]
        d = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-9)
        r[j - 1] = (d - d0) - rd[j - 1]
        jac[j - 1, 0] = dx / d - dx0 / d0
        jac[j - 1, 1] = dy / d - dy0 / d0
        jac[j - 1, 2] = dz / d - dz0 / d0
        cost += r[j - 1] * r[j - 1]
    return cost


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _solve3(a, b):
    """Solve the 3 × 3 system a x = b in place (b becomes x), Gaussian elimination with partial pivoting."""
    for col in range(3):
        piv = col
        for row in range(col + 1, 3):
            if abs(a[row, col]) > abs(a[piv, col]):
                piv = row
        if piv != col:
            for n in range(3):
                a[col, n], a[piv, n] = a[piv, n], a[col, n]
            b[col], b[piv] = b[piv], b[col]
        for row in range(col + 1, 3):
            f = a[row, col] / a[col, col]
            for n in range(col, 3):
                a[row, n] -= f * a[col, n]
            b[row] -= f * b[col]
    for row in range(2, -1, -1):
        s = b[row]
        for n in range(row + 1, 3):
            s -= a[row, n] * b[n]
        b[row] = s / a[row, row]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _normal_3(jac, r, m1, jtj, jtr):
    for i in range(3):
        jtr[i] = 0.0
        for j in range(3):
            jtj[i, j] = 0.0
    for k in range(m1):
        for i in range(3):
            jtr[i] += jac[k, i] * r[k]
            for j in range(3):
                jtj[i, j] += jac[k, i] * jac[k, j]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _lm_3d(p, mics, rd, n_iterations, r, jac, r_new, jac_new, a, g):
    """:func:`acoustlab.toolkit.solve3d.polish_3d` for one start p (3,), refined in place; returns the cost (m²)."""
    m1 = mics.shape[0] - 1
    cost = _residuals_3d(p[0], p[1], p[2], mics, rd, r, jac)
    lam = 1e-3
    for _ in range(n_iterations):
        _normal_3(jac, r, m1, a, g)
        scale = (a[0, 0] + a[1, 1] + a[2, 2]) / 3 + 1e-12
        for i in range(3):
            a[i, i] += lam * scale
        _solve3(a, g)
        nx, ny, nz = p[0] - g[0], p[1] - g[1], p[2] - g[2]
        cost_new = _residuals_3d(nx, ny, nz, mics, rd, r_new, jac_new)
        better = cost_new < cost
        if better:
            p[0], p[1], p[2], cost = nx, ny, nz, cost_new
            for k in range(m1):
                r[k] = r_new[k]
                for i in range(3):
                    jac[k, i] = jac_new[k, i]
        lam = min(max(lam * 0.3 if better else lam * 10.0, 1e-12), 1e8)
        if np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]) < 1e-9 or (not better and lam >= 1e8):
            break
    return cost


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _det3(a):
    return a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]) - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0]) \
        + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _coplanar_roots(mics, rd, frame, local, a, g, row, cand):
    """Coplanar mics: least squares in the plane coordinates and r₀ (rows −2 local_j, −2 d_j; right side d_j² − |q_j|²),
    then both mirror images ±w off the plane into cand (2, 3) (left NaN without a solution with r₀ ≥ 0)."""
    m = mics.shape[0]
    for i in range(3):
        g[i] = 0.0
        for j in range(3):
            a[i, j] = 0.0
    for j in range(1, m):
        row[0], row[1], row[2] = -2 * local[j - 1, 0], -2 * local[j - 1, 1], -2 * rd[j - 1]
        qq = (mics[j, 0] - mics[0, 0]) ** 2 + (mics[j, 1] - mics[0, 1]) ** 2 + (mics[j, 2] - mics[0, 2]) ** 2
        for i in range(3):
            g[i] += row[i] * (rd[j - 1] ** 2 - qq)
            for k in range(3):
                a[i, k] += row[i] * row[k]
    if _det3(a) > 1e-12 * (a[0, 0] + a[1, 1] + a[2, 2]) ** 3:  # normal equations, well conditioned
        _solve3(a, g)
    else:  # (near-)rank-deficient, e.g. equal arrival times: the pseudo-inverse's minimum-norm solution, as numpy
        design = np.empty((m - 1, 3))
        rhs = np.empty(m - 1)
        for j in range(1, m):
            design[j - 1, 0], design[j - 1, 1], design[j - 1, 2] = -2 * local[j - 1, 0], -2 * local[j - 1, 1], -2 * rd[j - 1]
            rhs[j - 1] = rd[j - 1] ** 2 - ((mics[j, 0] - mics[0, 0]) ** 2 + (mics[j, 1] - mics[0, 1]) ** 2 + (mics[j, 2] - mics[0, 2]) ** 2)
        solution = np.linalg.pinv(design) @ rhs
        g[0], g[1], g[2] = solution[0], solution[1], solution[2]
    s0, s1, r0 = g[0], g[1], g[2]
    if np.isfinite(s0) and np.isfinite(s1) and np.isfinite(r0) and r0 >= 0:
        w = np.sqrt(max(r0 * r0 - s0 * s0 - s1 * s1, 0.0))
        for n in range(2):
            sign = 1.0 if n == 0 else -1.0
            for i in range(3):
                cand[n, i] = (s0 * frame[0, i] + s1 * frame[1, i] + sign * w * frame[2, i]) + mics[0, i]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _quadratic_roots_3d(mics, rd, pinv3, u, v, cand):
    """Mics off a plane: p = u + v r₀ and |p − m₀| = r₀, a quadratic in r₀; its roots ≥ 0 (the vertex twice where the
    discriminant is negative) into cand (2, 3)."""
    m = mics.shape[0]
    for i in range(3):
        u[i] = v[i] = 0.0
    for j in range(1, m):
        b = rd[j - 1] ** 2 - ((mics[j, 0] - mics[0, 0]) ** 2 + (mics[j, 1] - mics[0, 1]) ** 2 + (mics[j, 2] - mics[0, 2]) ** 2)
        for i in range(3):
            u[i] += b * pinv3[i, j - 1]
            v[i] += 2 * rd[j - 1] * pinv3[i, j - 1]
    a2 = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) - 1
    a1 = 2 * (u[0] * v[0] + u[1] * v[1] + u[2] * v[2])
    a0 = u[0] * u[0] + u[1] * u[1] + u[2] * u[2]
    disc = a1 * a1 - 4 * a2 * a0
    root = np.sqrt(max(disc, 0.0))
    for n in range(2):
        r0 = (-a1 / (2 * a2)) if disc < 0 else ((-a1 + root) / (2 * a2) if n == 0 else (-a1 - root) / (2 * a2))
        if np.isfinite(r0) and r0 >= 0:
            for i in range(3):
                cand[n, i] = (u[i] + v[i] * r0) + mics[0, i]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _height_gdop(a):
    """√((JᵀJ)⁻¹)₂₂ for the 3 × 3 normal matrix a: the inverse where λ_min > 10⁻¹² λ_max (then it is the pseudo-inverse),
    else numpy's hermitian pseudo-inverse (a source in the mics' plane, where the height is unobservable to first order)."""
    det = _det3(a)
    if det > 1e-12 * (a[0, 0] + a[1, 1] + a[2, 2]) ** 3:
        return np.sqrt(max((a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) / det, 0.0))
    if not np.isfinite(det):
        return np.nan
    w, vec = np.linalg.eigh(a)
    cutoff = 1e-15 * max(abs(w[0]), abs(w[1]), abs(w[2]))
    cov = 0.0
    for k in range(3):
        if abs(w[k]) > cutoff:
            cov += vec[2, k] * vec[2, k] / w[k]
    return np.sqrt(max(cov, 0.0))


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _fix_3d(mics, rd, coplanar, frame, local, pinv3, residual_tie, n_iterations, work, buf, out):
    """The 3-D fix of one event; buf (5, 3) scratch. out: x, y, z, cost (m², inf if none), height_ambiguous, height_gdop, n_roots, gdop."""
    m = mics.shape[0]
    r, jac, r_new, jac_new, a, g = work
    cand = buf[:2]
    for n in range(2):
        for i in range(3):
            cand[n, i] = np.nan
    if coplanar:
        _coplanar_roots(mics, rd, frame, local, a, g, buf[2], cand)
    else:
        _quadratic_roots_3d(mics, rd, pinv3, buf[3], buf[4], cand)
    valid_0 = np.isfinite(cand[0, 0]) and np.isfinite(cand[0, 1]) and np.isfinite(cand[0, 2])
    valid_1 = np.isfinite(cand[1, 0]) and np.isfinite(cand[1, 1]) and np.isfinite(cand[1, 2])
    cost_0 = _lm_3d(cand[0], mics, rd, n_iterations, r, jac, r_new, jac_new, a, g) if valid_0 else np.inf
    cost_1 = _lm_3d(cand[1], mics, rd, n_iterations, r, jac, r_new, jac_new, a, g) if valid_1 else np.inf
    # above ground where possible; among fits within the tie of the best, the upper one (the first where equal)
    above_0, above_1 = valid_0 and cand[0, 2] >= 0, valid_1 and cand[1, 2] >= 0
    usable_0, usable_1 = (above_0, above_1) if (above_0 or above_1) else (valid_0, valid_1)
    fit_0, fit_1 = np.sqrt(cost_0 / (m - 1)), np.sqrt(cost_1 / (m - 1))
    best_fit = min(fit_0 if usable_0 else np.inf, fit_1 if usable_1 else np.inf)
    tie_0, tie_1 = usable_0 and fit_0 <= best_fit + residual_tie, usable_1 and fit_1 <= best_fit + residual_tie
    choice = 1 if tie_1 and (not tie_0 or cand[1, 2] > cand[0, 2]) else 0
    out[0], out[1], out[2], out[3] = cand[choice, 0], cand[choice, 1], cand[choice, 2], cost_1 if choice else cost_0
    two_above = tie_0 and above_0 and tie_1 and above_1
    out[4] = 1.0 if (two_above and abs(cand[0, 2] - cand[1, 2]) > 2 * residual_tie) else 0.0
    out[6] = int(valid_0) + int(valid_1)
    out[5] = out[7] = np.nan
    if out[6]:
        px, py, pz = out[0], out[1], out[2]
        _residuals_3d(px if np.isfinite(px) else 0.0, py if np.isfinite(py) else 0.0, pz if np.isfinite(pz) else 0.0, mics, rd, r, jac)
        _normal_3(jac, r, m - 1, a, g)
        out[7] = _gdop(a[0, 0], a[0, 1], a[1, 1])  # the x, y columns are the horizontal GDOP's gradients at this height
        out[5] = _height_gdop(a)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _solve_batch(mics, tdoa, speed, height, levels, use_levels, dims, fallback_2d, pinv2, box, box_wide, coplanar, frame, local, pinv3,
                 residual_tie, n_iterations, out):
    """Every event's fix into out (B, 12): x, y, residual (m), converged, conditioning, gdop, n_roots, source height,
    height_gdop, height_ambiguous, dimensions_used and the residual in s, as :class:`HyperbolicSolver` reports them."""
    bsz, m = tdoa.shape
    rd = np.empty(m - 1)
    w2 = (np.empty((2, m - 1)), np.empty((2, m - 1, 2)), np.empty(m - 1), np.empty((m - 1, 2)))
    w3 = (np.empty(m - 1), np.empty((m - 1, 3)), np.empty(m - 1), np.empty((m - 1, 3)), np.empty((3, 3)), np.empty(3))
    fix2 = np.empty(7)
    buf2 = np.empty((6, 2))
    buf3 = np.empty((5, 3))
    fix3 = np.empty(8)
    for b in range(bsz):
        finite = np.isfinite(speed[b])
        for j in range(m):
            finite = finite and np.isfinite(tdoa[b, j])
        for j in range(1, m):
            rd[j - 1] = speed[b] * (tdoa[b, j] - tdoa[b, 0]) if finite else 0.0
        o = out[b]
        for n in range(12):
            o[n] = np.nan
        if dims == 3:
            _fix_3d(mics, rd, coplanar, frame, local, pinv3, residual_tie, max(n_iterations, 1), w3, buf3, fix3)
            res = np.sqrt(fix3[3] / (m - 1))
            ok = finite and np.isfinite(fix3[0]) and np.isfinite(fix3[1]) and np.isfinite(fix3[2])
            usable = ok and box_wide[0] <= fix3[0] <= box_wide[2] and box_wide[1] <= fix3[1] <= box_wide[3] and fix3[2] >= 0
            if usable or not fallback_2d:
                if ok:
                    o[0], o[1], o[2] = fix3[0], fix3[1], res
                    o[5] = fix3[7]
                    o[7], o[8], o[9], o[10] = fix3[2], fix3[5], fix3[4], 3.0
                    o[11] = res / speed[b]
                o[3] = ok and res < 1e3
                o[6] = fix3[6]
                continue
        # 2-D at the assumed height (dims 2, or the 3-D fix failed or is implausible)
        _fix_2d(mics, rd, height, pinv2, box, residual_tie, n_iterations, levels[b], use_levels, w2, buf2, fix2)
        if finite:
            o[0], o[1], o[2], o[3], o[4], o[5] = fix2[0], fix2[1], fix2[2], fix2[3], fix2[4], fix2[5]
            o[11] = fix2[2] / speed[b]
        else:
            o[3] = 0.0
        o[6], o[7], o[10] = fix2[6], height, 2.0


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
