"""TDOA maths shared by solver plugins: residuals, batch Levenberg–Marquardt, energy consistency.

Hand-written because SciPy's least-squares solvers take one problem per call (≈4 ms per event);
here every event and start point iterates together as arrays.
"""

from __future__ import annotations

import warnings

import numpy as np

from acoustlab.core.contracts import SolverInputs


def solver_inputs(inputs: SolverInputs, own_height_m: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Validate a solver's inputs and bring them to (M, 3) mics, (B, M) TDOAs, (B,) speeds and a height.

    Parameters
    ----------
    inputs : SolverInputs
        The batch (see ``acoustlab.core.contracts.SolverInputs``).
    own_height_m : float, optional
        The solver's own configured source height, m; it takes precedence over
        ``inputs.source_height_m``; with neither, the mean mic height is assumed.

    Raises
    ------
    ValueError
        Naming the field and the expected shape.
    """
    mics = np.asarray(inputs.mic_positions_m, dtype=float)
    if mics.ndim != 2 or mics.shape[1] not in (2, 3) or mics.shape[0] < 3:
        raise ValueError(f"mic_positions_m must be (M>=3, 2|3); got shape {mics.shape}")
    if mics.shape[1] == 2:
        mics = np.column_stack([mics, np.zeros(len(mics))])
    tdoa = np.atleast_2d(np.asarray(inputs.tdoa_s, dtype=float))
    if tdoa.shape[1] != mics.shape[0]:
        raise ValueError(f"tdoa_s must be (B, {mics.shape[0]}); got shape {tdoa.shape}")
    speed = np.broadcast_to(np.asarray(inputs.speed_of_sound_m_s, dtype=float), (tdoa.shape[0],))
    if own_height_m is not None:
        height = float(own_height_m)
    elif inputs.source_height_m is not None:
        height = float(inputs.source_height_m)
    else:
        height = mics[:, 2].mean()
    return mics, tdoa, speed, height


def range_residuals(p: np.ndarray, mics: np.ndarray, height: np.ndarray, rd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Range-difference residuals and their Jacobian.

    Parameters
    ----------
    p : numpy.ndarray
        (..., 2) candidate horizontal positions in m.
    mics : numpy.ndarray
        (M, 3) mic positions in m.
    height : numpy.ndarray
        (...) source heights in m.
    rd : numpy.ndarray
        (..., M−1) measured range differences c·(t_j − t_0) in m, broadcastable to p's batch shape.

    Returns
    -------
    r : numpy.ndarray
        (..., M−1) residuals (‖p − m_j‖ − ‖p − m_0‖) − rd_j in m.
    jac : numpy.ndarray
        (..., M−1, 2) derivatives with respect to p.
    """
    diff = p[..., None, :] - mics[:, :2]
    dz = height[..., None] - mics[:, 2]
    dist = np.maximum(np.sqrt((diff**2).sum(-1) + dz**2), 1e-9)
    r = (dist[..., 1:] - dist[..., :1]) - rd
    grad = diff / dist[..., None]
    return r, grad[..., 1:, :] - grad[..., :1, :]


def levenberg_marquardt(
    p0: np.ndarray, mics: np.ndarray, height: np.ndarray, rd: np.ndarray, n_iterations: int = 100
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimise the squared range-difference residuals from start points ``p0`` (..., 2), in batch.

    Every problem iterates until its proposed step is below 1 nm, or its damping reaches 10⁸
    without improvement, or ``n_iterations`` pass; only the problems still running are computed.

    Returns
    -------
    p : numpy.ndarray
        (..., 2) refined positions in m.
    cost : numpy.ndarray
        (...) sum of squared residuals in m².
    step : numpy.ndarray
        (...) size of the last accepted step in m (inf if none was accepted).
    """
    batch = np.shape(p0)[:-1]
    p = np.array(np.broadcast_to(p0, (*batch, 2)), dtype=float).reshape(-1, 2)
    h = np.broadcast_to(np.asarray(height, dtype=float), batch).reshape(-1)
    rd = np.broadcast_to(rd, (*batch, rd.shape[-1])).reshape(-1, rd.shape[-1])
    lam = np.full(len(p), 1e-2)
    r, jac = range_residuals(p, mics, h, rd)
    cost = (r**2).sum(-1)
    step_norm = np.full(len(p), np.inf)
    act = np.arange(len(p))
    for _ in range(n_iterations):
        if act.size == 0:
            break
        ja, ra, la = jac[act], r[act], lam[act]
        jtj = np.einsum("bki,bkj->bij", ja, ja)
        jtr = np.einsum("bki,bk->bi", ja, ra)
        scale = (jtj[:, 0, 0] + jtj[:, 1, 1]) / 2 + 1e-9
        a00 = jtj[:, 0, 0] + la * scale
        a11 = jtj[:, 1, 1] + la * scale
        a01 = jtj[:, 0, 1]
        det = a00 * a11 - a01 * a01
        det = np.where(np.abs(det) < 1e-18, 1e-18, det)
        step = -np.stack([a11 * jtr[:, 0] - a01 * jtr[:, 1], a00 * jtr[:, 1] - a01 * jtr[:, 0]], axis=-1) / det[:, None]
        p_new = p[act] + step
        r_new, jac_new = range_residuals(p_new, mics, h[act], rd[act])
        cost_new = (r_new**2).sum(-1)
        better = cost_new < cost[act]
        won = act[better]
        p[won], r[won], jac[won], cost[won] = p_new[better], r_new[better], jac_new[better], cost_new[better]
        proposed = np.sqrt((step**2).sum(-1))
        step_norm[won] = proposed[better]
        lam[act] = np.clip(np.where(better, la * 0.3, la * 10.0), 1e-12, 1e8)
        # a problem stops when its proposed step is below 1 nm or it can no longer improve
        done = (proposed < 1e-9) | (~better & (lam[act] >= 1e8))
        act = act[~done]
    return p.reshape(*batch, 2), cost.reshape(batch), step_norm.reshape(batch)


def energy_residual_db(levels_db: np.ndarray, mics: np.ndarray, position_m: np.ndarray, height_m: float | np.ndarray) -> np.ndarray:
    """RMS over mic pairs of observed minus 1/r-predicted level differences, in dB.

    For mics i, j the received levels should differ by −20 log10(r_i / r_j) if the source is at the
    candidate position (spherical spreading, equal mic gains). A large residual says the candidate
    is inconsistent with the energy pattern.

    Parameters
    ----------
    levels_db : numpy.ndarray
        (B, M) received levels in the call band, dB.
    mics : numpy.ndarray
        (M, 3) mic positions in m.
    position_m : numpy.ndarray
        (B, 2) candidate horizontal positions in m (or (B, K, 2) for K candidates per event).
    height_m : float or numpy.ndarray
        Source height in m.

    Returns
    -------
    numpy.ndarray
        (B,) or (B, K) residuals in dB (NaN where levels are missing).
    """
    pos = np.asarray(position_m, dtype=float)
    lv = np.asarray(levels_db, dtype=float)
    if pos.ndim == 3:
        lv = lv[:, None, :]
    dist = np.sqrt(((pos[..., None, :] - mics[:, :2]) ** 2).sum(-1) + (np.asarray(height_m)[..., None] - mics[:, 2]) ** 2)
    e = lv + 20 * np.log10(np.maximum(dist, 1e-3))
    m = mics.shape[0]
    i, j = np.triu_indices(m, 1)
    return np.sqrt(np.mean((e[..., i] - e[..., j]) ** 2, axis=-1))


def candidate_misfit_m(
    position_m: np.ndarray,
    height_m: np.ndarray,
    mics: np.ndarray,
    pairs: np.ndarray,
    candidate_lags_s: np.ndarray,
    speed_m_s: np.ndarray,
) -> np.ndarray:
    """How well positions explain the measured time differences: the misfit within which all but a quarter of the pairs
    fall, each pair at its closest GCC candidate, m.

    For each mic pair (i, j) the position predicts the lag t_j − t_i = (‖p − m_j‖ − ‖p − m_i‖) / c;
    the pair's misfit is the smallest |c·lag − predicted range difference| over its candidates
    (any of them may be the direct path). The event's misfit is the ⌈P − ⌊P/4⌋⌉-th smallest of the
    P pairs that have a candidate (``UNEXPLAINED_SHARE``): a few pairs whose candidates are all
    wrong cannot dominate it, as they do an RMS (on a 14-mic array, 15 such pairs of 91 made a
    position 53 m off look better than the right one), while a position must still explain most
    pairs. On 3 mics (3 pairs, which close one triangle) every pair must be explained: two pairs
    met by a decoy and a direct path would otherwise pass anywhere on their hyperbolas.
    Expressed as range differences (m) so that it compares across temperatures.

    Parameters
    ----------
    position_m : numpy.ndarray
        (E, 2) horizontal positions, m (NaN rows give NaN).
    height_m : numpy.ndarray
        (E,) source heights, m.
    mics : numpy.ndarray
        (M, 3) mic positions, m.
    pairs : numpy.ndarray
        (P, 2) mic indices (i, j) of the candidate columns.
    candidate_lags_s : numpy.ndarray
        (E, P, K) candidate lags t_j − t_i, s (NaN where a pair has fewer candidates).
    speed_m_s : numpy.ndarray
        (E,) speed of sound, m/s.

    Returns
    -------
    numpy.ndarray
        (E,) misfit in m; NaN where the position is not finite or no pair has a candidate.
    """
    position = np.asarray(position_m, dtype=float)
    pairs = np.asarray(pairs, dtype=int)
    source = np.column_stack([position, np.asarray(height_m, dtype=float)])
    distance = np.sqrt(((source[:, None, :] - mics[None, :, :]) ** 2).sum(-1))  # (E, M)
    predicted = distance[:, pairs[:, 1]] - distance[:, pairs[:, 0]]  # (E, P)
    observed = np.asarray(candidate_lags_s, dtype=float) * np.asarray(speed_m_s, dtype=float)[:, None, None]
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pairs: no candidate
        per_pair = np.nanmin(np.abs(observed - predicted[..., None]), axis=-1)  # (E, P)
    return _all_but_a_share(per_pair, UNEXPLAINED_SHARE)


#: The share of an event's mic pairs whose misfit ``candidate_misfit_m`` leaves out (the largest ones), rounded down.
UNEXPLAINED_SHARE = 0.25


def _all_but_a_share(per_pair: np.ndarray, share: float) -> np.ndarray:
    """(E,) the ``P − ⌊share·P⌋``-th smallest finite value of each row of (E, P) ``per_pair`` (NaN for a row without one)."""
    valid = np.isfinite(per_pair).sum(axis=1)
    ordered = np.sort(np.where(np.isfinite(per_pair), per_pair, np.inf), axis=1)  # NaN pairs last
    rank = np.maximum(valid - np.floor(share * valid).astype(int) - 1, 0)
    value = np.take_along_axis(ordered, rank[:, None], axis=1)[:, 0]
    return np.where(valid > 0, value, np.nan)
