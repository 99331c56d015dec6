"""Array geometry: convex hulls, source-region sampling, bounding boxes (metres)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull

from acoustlab.core.errors import ConfigError


def collinearity_ratio(points_xy: np.ndarray) -> float:
    """Smallest over largest singular value of the centred 2-D points (0 for collinear points).

    Parameters
    ----------
    points_xy : numpy.ndarray
        (N, 2) positions in m.

    Returns
    -------
    float
        Dimensionless ratio in [0, 1].
    """
    centred = points_xy - points_xy.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    return float(s[-1] / s[0]) if s[0] > 0 else 0.0


def hull_polygon(points_xy: np.ndarray) -> np.ndarray:
    """Vertices (K, 2) of the 2-D convex hull in counter-clockwise order."""
    hull = ConvexHull(points_xy)
    return points_xy[hull.vertices]


def distance_to_polygon_m(points_xy: np.ndarray, polygon_xy: np.ndarray) -> np.ndarray:
    """Distance from each point to a convex polygon (0 inside), vectorised.

    Parameters
    ----------
    points_xy : numpy.ndarray
        (N, 2) query points in m.
    polygon_xy : numpy.ndarray
        (K, 2) convex polygon vertices in order.

    Returns
    -------
    numpy.ndarray
        (N,) distances in m.
    """
    a = polygon_xy
    b = np.roll(polygon_xy, -1, axis=0)
    ab = b - a  # (K, 2)
    ap = points_xy[:, None, :] - a[None, :, :]  # (N, K, 2)
    # inside a convex polygon: on the same side of every edge (either orientation of the vertices)
    cross = ab[None, :, 0] * ap[..., 1] - ab[None, :, 1] * ap[..., 0]  # (N, K)
    inside = (cross >= 0).all(axis=1) | (cross <= 0).all(axis=1)
    t = np.clip((ap * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    d = np.sqrt(((points_xy[:, None, :] - closest) ** 2).sum(-1)).min(axis=1)
    return np.where(inside, 0.0, d)


def source_region(mic_positions_m: np.ndarray, hull_expansion: float) -> tuple[np.ndarray, float]:
    """The region sources are drawn from: the mics' 2-D hull and its buffer distance.

    Returns
    -------
    polygon_xy : numpy.ndarray
        (K, 2) hull vertices in m.
    buffer_m : float
        Buffer distance = ``hull_expansion`` × largest mic-to-mic distance, in m.
    """
    xy = np.asarray(mic_positions_m, dtype=float)[:, :2]
    d = np.sqrt(((xy[:, None] - xy[None]) ** 2).sum(-1)).max()
    return hull_polygon(xy), float(hull_expansion * d)


def sample_in_expanded_hull(rng: np.random.Generator, mic_positions_m: np.ndarray, hull_expansion: float, n: int) -> np.ndarray:
    """Draw points uniformly inside the mics' convex hull grown by a buffer (rejection sampling).

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    mic_positions_m : numpy.ndarray
        (M, 2) or (M, 3) microphone positions in m.
    hull_expansion : float
        Buffer as a fraction of the largest mic-to-mic distance.
    n : int
        Number of points.

    Returns
    -------
    numpy.ndarray
        (n, 2) positions in m.
    """
    polygon, buffer_m = source_region(mic_positions_m, hull_expansion)
    low = polygon.min(axis=0) - buffer_m
    high = polygon.max(axis=0) + buffer_m
    out = np.empty((0, 2))
    while out.shape[0] < n:
        cand = rng.uniform(low, high, size=(max(2 * (n - out.shape[0]), 16), 2))
        keep = distance_to_polygon_m(cand, polygon) <= buffer_m
        out = np.vstack([out, cand[keep]])
    return out[:n]


def bounding_box(mic_positions_m: np.ndarray, margin_fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned 2-D bounding box of the mics grown by ``margin_fraction`` × array extent.

    The array extent is the largest mic-to-mic distance.

    Returns
    -------
    low, high : numpy.ndarray
        (2,) corners in m.
    """
    xy = np.asarray(mic_positions_m, dtype=float)[:, :2]
    extent = np.sqrt(((xy[:, None] - xy[None]) ** 2).sum(-1)).max()
    if margin_fraction < 0:
        raise ConfigError(f"bounding-box margin_fraction must be >= 0; got {margin_fraction}")
    m = margin_fraction * extent
    return xy.min(axis=0) - m, xy.max(axis=0) + m


def gdop(mic_positions_m: np.ndarray, source_position_m: np.ndarray) -> np.ndarray:
    """Geometric dilution of precision of TDOA localization, vectorised over source positions.

    With unit vectors u_i from mic i to the source, the range differences to mic 0 have the
    Jacobian rows h_j = u_j − u_0 (j = 1…M−1); GDOP = √trace((HᵀH)⁻¹), the factor from a
    range-difference standard deviation (m) to the RMS position error (m). Mic heights are used when
    given; the source height is taken from ``source_position_m`` when it has 3 columns, else as the
    mean mic height.

    Parameters
    ----------
    mic_positions_m : numpy.ndarray
        (M, 2) or (M, 3) microphone positions in m.
    source_position_m : numpy.ndarray
        (B, 2) or (B, 3) source positions in m.

    Returns
    -------
    numpy.ndarray
        (B,) dimensionless GDOP (inf where the geometry is singular).
    """
    mics = np.asarray(mic_positions_m, dtype=float)
    src = np.atleast_2d(np.asarray(source_position_m, dtype=float))
    if mics.shape[1] == 2:
        mics = np.column_stack([mics, np.zeros(len(mics))])
    if src.shape[1] == 2:
        src = np.column_stack([src, np.full(len(src), mics[:, 2].mean())])
    diff = src[:, None, :2] - mics[None, :, :2]  # horizontal unknowns only
    dist = np.sqrt(((src[:, None, :] - mics[None, :, :]) ** 2).sum(-1))
    u = diff / np.maximum(dist, 1e-9)[..., None]
    h = u[:, 1:, :] - u[:, :1, :]  # (B, M-1, 2)
    hth = np.einsum("bki,bkj->bij", h, h)
    det = hth[:, 0, 0] * hth[:, 1, 1] - hth[:, 0, 1] ** 2
    trace_inv = (hth[:, 0, 0] + hth[:, 1, 1]) / np.where(det > 1e-12, det, np.nan)
    out = np.sqrt(trace_inv)
    return np.where(np.isfinite(out), out, np.inf)


def tdoa_crb_s(snr_db: np.ndarray, rms_bandwidth_hz: np.ndarray, duration_s: np.ndarray, bandwidth_hz: np.ndarray) -> np.ndarray:
    """Cramér–Rao bound on a time-delay estimate between two sensors, in s (standard deviation).

    For a signal with RMS bandwidth β observed for T seconds over a band W at the same per-sensor
    SNR r at both sensors, var(τ) ≥ (1 + 2r) / r² / (8 π² β² T W) (the two-sensor Knapp–Carter
    bound; at high SNR it is 1 / (4 π² β² r T W): both sensors' noise counts, so it is √2 above the
    single-noisy-sensor form). A Monte-Carlo of the cross-correlation estimator matches it within a
    few per cent (``tests/test_physics.py``).

    Parameters
    ----------
    snr_db : array_like
        Per-sensor signal-to-noise ratio within the band, dB.
    rms_bandwidth_hz : array_like
        RMS bandwidth β = √(∫ f² S / ∫ S), Hz.
    duration_s : array_like
        Observation time T, s.
    bandwidth_hz : array_like
        Band W over which the SNR holds, Hz.
    """
    snr = 10 ** (np.asarray(snr_db, dtype=float) / 10)
    tw = np.maximum(np.asarray(duration_s, dtype=float) * np.asarray(bandwidth_hz, dtype=float), 1.0)
    return np.sqrt((1 + 2 * snr) / snr**2 / (8 * np.pi**2 * np.asarray(rms_bandwidth_hz, dtype=float) ** 2 * tw))


def position_crb_m(
    mic_positions_m: np.ndarray,
    source_position_m: np.ndarray,
    snr_db: np.ndarray,
    rms_bandwidth_hz: np.ndarray,
    duration_s: np.ndarray,
    bandwidth_hz: np.ndarray,
    speed_of_sound_m_s: float | np.ndarray,
) -> np.ndarray:
    """Cramér–Rao bound on the RMS 2-D position error, m: GDOP × c × σ_τ (equal, independent TDOA errors).

    Returns
    -------
    numpy.ndarray
        (B,) bound in m for the (B, 2|3) source positions.
    """
    sigma = tdoa_crb_s(snr_db, rms_bandwidth_hz, duration_s, bandwidth_hz)
    return gdop(mic_positions_m, source_position_m) * np.asarray(speed_of_sound_m_s, dtype=float) * sigma
