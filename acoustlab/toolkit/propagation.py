"""Outdoor propagation physics: ground impedance and reflection, trunk scattering, occlusion.

Conventions follow the project's physics notes: time factor e^{−iωt}, k = 2πf/c; R1 is the
direct path, R2 the path via the ground image. Functions return transfer functions in that
convention; ``to_fft_convention`` converts to NumPy's FFT convention (e^{−i2πft}).
All inputs in SI units (Hz, m, m/s) except flow resistivity in kPa·s·m⁻² as tabulated.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.special import jvp, wofz, yvp

IMPEDANCE_MODELS = ("delany_bazley", "miki", "rigid")


def _ratio(frequency_hz: np.ndarray, flow_resistivity_kpa_s_m2: float) -> np.ndarray:
    """X = f / σ with σ in kPa·s·m⁻² (equivalently 1000 f / σ[Pa·s·m⁻²]); guarded against f = 0."""
    return np.maximum(np.asarray(frequency_hz, dtype=float), 1.0) / float(flow_resistivity_kpa_s_m2)


def ground_impedance(
    frequency_hz: np.ndarray,
    flow_resistivity_kpa_s_m2: float,
    model: str = "miki",
    layer_thickness_m: float | None = None,
    speed_of_sound_m_s: float = 343.0,
) -> np.ndarray:
    """Normalised surface impedance Z of a porous ground (e^{−iωt} convention, Im Z > 0).

    Delany–Bazley (1970): Z = 1 + 9.08 X^−0.75 + 11.9i X^−0.73, k_b/k = 1 + 10.8 X^−0.70 + 10.3i X^−0.59.
    Miki (1990): Z = 1 + 5.50 X^−0.632 + 8.43i X^−0.632, k_b/k = 1 + 7.81 X^−0.618 + 11.41i X^−0.618.
    With ``layer_thickness_m`` the porous layer is hard-backed (snow over ice, litter over
    rock): Z_d = Z · coth(−i k_b d).

    Parameters
    ----------
    frequency_hz : array_like
        Frequencies in Hz.
    flow_resistivity_kpa_s_m2 : float
        Effective flow resistivity σ in kPa·s·m⁻².
    model : {"miki", "delany_bazley", "rigid"}
        Impedance model; ``rigid`` gives Z = ∞ (returned as 1e12).
    layer_thickness_m : float, optional
        Thickness of a hard-backed porous layer in m.
    speed_of_sound_m_s : float
        Speed of sound in air (for k_b), m/s.

    Returns
    -------
    numpy.ndarray
        Complex normalised impedance, same shape as ``frequency_hz``.
    """
    f = np.asarray(frequency_hz, dtype=float)
    if model == "rigid":
        return np.full(f.shape, 1e12 + 0j)
    x = _ratio(f, flow_resistivity_kpa_s_m2)
    if model == "delany_bazley":
        z = 1 + 9.08 * x**-0.75 + 11.9j * x**-0.73
        kb_ratio = 1 + 10.8 * x**-0.70 + 10.3j * x**-0.59
    elif model == "miki":
        z = 1 + 5.50 * x**-0.632 + 8.43j * x**-0.632
        kb_ratio = 1 + 7.81 * x**-0.618 + 11.41j * x**-0.618
    else:
        raise ValueError(f"ground impedance model must be one of {IMPEDANCE_MODELS}; got {model!r}")
    if layer_thickness_m:
        k = 2 * np.pi * np.maximum(f, 1.0) / speed_of_sound_m_s
        arg = -1j * k * kb_ratio * float(layer_thickness_m)
        z = z / np.tanh(arg)
    return z


def spherical_reflection_coefficient(
    frequency_hz: np.ndarray, impedance: np.ndarray, r2_m: np.ndarray, cos_theta: np.ndarray, speed_of_sound_m_s: float
) -> np.ndarray:
    """Weyl–van der Pol spherical-wave reflection coefficient Q (e^{−iωt} convention).

    Q = R_p + (1 − R_p) F(w), R_p = (Z cosθ − 1)/(Z cosθ + 1), w = √(i k R2 / 2) (cosθ + 1/Z),
    F(w) = 1 + i √π w · wofz(w). At grazing incidence on soft ground R_p → −1 but the ground wave
    (1 − R_p) F keeps Q away from −1; on rigid ground Q = 1.

    Parameters
    ----------
    frequency_hz : numpy.ndarray
        (F,) frequencies in Hz.
    impedance : numpy.ndarray
        (F,) normalised ground impedance Z.
    r2_m, cos_theta : numpy.ndarray
        (...,) image-path lengths in m and cosines of the incidence angle from the normal,
        cos θ = (h_s + h_r)/R2.
    speed_of_sound_m_s : float
        Speed of sound in m/s.

    Returns
    -------
    numpy.ndarray
        (..., F) complex Q.
    """
    f = np.asarray(frequency_hz, dtype=float)
    z = np.asarray(impedance)
    r2 = np.asarray(r2_m, dtype=float)[..., None]
    cos_t = np.asarray(cos_theta, dtype=float)[..., None]
    k = 2 * np.pi * f / speed_of_sound_m_s
    rp = (z * cos_t - 1) / (z * cos_t + 1)
    w = np.sqrt(0.5j * k * r2) * (cos_t + 1 / z)
    # for rigid ground 1 − R_p = 0, so a non-finite F there (huge |w|) contributes nothing
    fw = 1 + 1j * np.sqrt(np.pi) * w * wofz(w)
    fw = np.where(np.isfinite(fw), fw, 0.0)
    return rp + (1 - rp) * fw


def to_fft_convention(transfer: np.ndarray) -> np.ndarray:
    """Convert an e^{−iωt} transfer function to NumPy's FFT convention (complex conjugate)."""
    return np.conj(transfer)


@lru_cache(maxsize=4)
def cylinder_scattering_table(ka_max: float = 150.0, n_ka: int = 400, n_angles: int = 181) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Far-field scattering function of a rigid infinite cylinder, tabulated over ka and angle.

    A(φ, ka) = Σ_{n≥0} ε_n sin γ_n e^{iγ_n} cos(nφ), tan γ_n = J_n'(ka)/Y_n'(ka) (Morse & Ingard),
    with φ = 0 forward scatter; the scattered pressure of a unit plane wave is
    A · √(2/(π k r)) e^{i(kr + π/4)}. Terms up to n = ka + 20 (enough for convergence).

    Returns
    -------
    ka : numpy.ndarray
        (n_ka,) log-spaced ka values from 0.01 to ``ka_max``.
    angles_rad : numpy.ndarray
        (n_angles,) φ from 0 to π (A is even in φ).
    table : numpy.ndarray
        (n_ka, n_angles) complex A.
    """
    ka = np.geomspace(0.01, ka_max, n_ka)
    phi = np.linspace(0.0, np.pi, n_angles)
    n = np.arange(int(ka_max) + 21)
    with np.errstate(all="ignore"):
        jp = jvp(n[None, :], ka[:, None])
        yp = yvp(n[None, :], ka[:, None])
    with np.errstate(invalid="ignore"):
        gamma = np.arctan2(jp, yp)  # any branch: sin γ e^{iγ} is π-periodic in γ
    # where the recurrences overflow (n ≫ ka) the term vanishes: J_n' → 0, |Y_n'| → ∞
    gamma = np.where(np.isfinite(gamma), gamma, 0.0)
    coef = np.where(n == 0, 1.0, 2.0)[None, :] * np.sin(gamma) * np.exp(1j * gamma)  # (n_ka, N)
    table = coef @ np.cos(np.outer(n, phi))  # (n_ka, n_angles)
    return ka, phi, table


def cylinder_scattering_magnitude(ka: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """|A(φ, ka)| by bilinear interpolation in (log ka, φ) of ``cylinder_scattering_table``."""
    ka_grid, phi_grid, table = cylinder_scattering_table()
    mag = np.abs(table)
    lk = np.log(np.clip(ka, ka_grid[0], ka_grid[-1]))
    lg = np.log(ka_grid)
    i = np.clip(np.searchsorted(lg, lk) - 1, 0, lg.size - 2)
    ti = (lk - lg[i]) / (lg[i + 1] - lg[i])
    ang = np.abs(np.mod(np.asarray(angle_rad) + np.pi, 2 * np.pi) - np.pi)  # fold into [0, π]
    step = phi_grid[1] - phi_grid[0]
    j = np.clip((ang / step).astype(int), 0, phi_grid.size - 2)
    tj = (ang - phi_grid[j]) / step
    return mag[i, j] * (1 - ti) * (1 - tj) + mag[i + 1, j] * ti * (1 - tj) + mag[i, j + 1] * (1 - ti) * tj + mag[i + 1, j + 1] * ti * tj


def segment_trunk_clearance(a_xy: np.ndarray, b_xy: np.ndarray, trees_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from each trunk centre to each segment a→b, and where along it the foot lies.

    Parameters
    ----------
    a_xy, b_xy : numpy.ndarray
        (P, 2) segment ends in m.
    trees_xy : numpy.ndarray
        (T, 2) trunk centres in m.

    Returns
    -------
    distance_m : numpy.ndarray
        (P, T) perpendicular distance from trunk centre to the segment, in m.
    fraction : numpy.ndarray
        (P, T) position of the foot of the perpendicular along a→b (0 at a, 1 at b).
    """
    ab = b_xy - a_xy
    length2 = np.maximum((ab**2).sum(-1), 1e-12)
    at = trees_xy[None, :, :] - a_xy[:, None, :]
    t = (at * ab[:, None, :]).sum(-1) / length2[:, None]
    closest = a_xy[:, None, :] + np.clip(t, 0, 1)[..., None] * ab[:, None, :]
    dist = np.sqrt(((trees_xy[None] - closest) ** 2).sum(-1))
    return dist, t


def trunk_detour_m(d_source_m: np.ndarray, d_receiver_m: np.ndarray, radius_m: np.ndarray, offset_m: np.ndarray) -> np.ndarray:
    """Extra path length of the shorter way around a trunk that blocks a straight path.

    The sound passes the trunk on the side nearer the path: the detour is the path through the
    point at distance ``radius_m`` from the centre on that side, minus the straight path.

    Parameters
    ----------
    d_source_m, d_receiver_m : numpy.ndarray
        Distances along the path from source and receiver to the foot of the trunk centre, in m.
    radius_m : numpy.ndarray
        Trunk radius in m.
    offset_m : numpy.ndarray
        Perpendicular distance of the trunk centre from the straight path (< radius), in m.

    Returns
    -------
    numpy.ndarray
        Detour δ ≥ 0 in m.
    """
    clear = radius_m - offset_m  # how far the path must move sideways
    return np.sqrt(d_source_m**2 + clear**2) + np.sqrt(d_receiver_m**2 + clear**2) - (d_source_m + d_receiver_m)


def occlusion_attenuation_db(frequency_hz: np.ndarray, detour_m: np.ndarray, speed_of_sound_m_s: float) -> np.ndarray:
    """Insertion loss of a trunk in the direct path, from Maekawa's diffraction approximation.

    With Fresnel number N = 2δ/λ, one edge gives 10 log10(3 + 20 N) dB. Sound bends round both
    sides of the trunk (−3 dB for two incoherent paths) and a trunk that only grazes the path
    costs nothing, so the loss used is 10 log10(1 + 20 N / 3) dB: 0 at N = 0, Maekawa's edge loss
    minus 4.8 dB for large N. A trunk shadows only when it is close to the source or the receiver
    (δ ≈ c²/2·(1/d1 + 1/d2) for a sideways clearance c), as in reality.

    Returns
    -------
    numpy.ndarray
        (..., F) attenuation in dB (≥ 0), broadcasting ``detour_m[..., None]`` over frequencies.
    """
    lam = speed_of_sound_m_s / np.maximum(np.asarray(frequency_hz, dtype=float), 1.0)
    n_fresnel = 2 * np.asarray(detour_m, dtype=float)[..., None] / lam
    return 10 * np.log10(1 + 20 * n_fresnel / 3)
