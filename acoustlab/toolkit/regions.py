"""Error ellipses: the shape from the local TDOA geometry, the size from conformal calibration.

Near the array a TDOA fix is about equally precise in every direction; outside it the hyperbolas
meet at grazing angles and the error stretches along the range direction. The shape matrix S is
(HᵀH)⁻¹ with H the range-difference Jacobian at the estimate (rows u_j − u_0 of horizontal unit
vectors), normalised to unit mean eigenvalue, so it carries orientation and elongation only. The
score of a calibration event is its Mahalanobis error √(dᵀS⁻¹d) divided by the error model's
prediction ê; the region at level 1 − α is {d : √(dᵀS⁻¹d) ≤ q̂ ê}, an ellipse whose semi-axes
are q̂ ê √λ₁,₂ (λ the eigenvalues of S). Split conformal on exchangeable positions gives it the
same coverage guarantee as the radius.
"""

from __future__ import annotations

import numpy as np


def shape_matrices(mic_positions_m: np.ndarray, position_m: np.ndarray, height_m: np.ndarray | float) -> np.ndarray:
    """(B, 2, 2) normalised shape matrices S at the positions (B, 2) (identity where the geometry is singular or unknown).

    Parameters
    ----------
    mic_positions_m : numpy.ndarray
        (M, 3) mic positions in m.
    position_m : numpy.ndarray
        (B, 2) estimates in m.
    height_m : float or numpy.ndarray
        Source height(s) in m.
    """
    mics = np.asarray(mic_positions_m, dtype=float)
    pos = np.nan_to_num(np.asarray(position_m, dtype=float))
    z = np.broadcast_to(np.asarray(height_m, dtype=float), (len(pos),))
    diff = pos[:, None, :] - mics[None, :, :2]
    dist = np.sqrt((diff**2).sum(-1) + (z[:, None] - mics[None, :, 2]) ** 2)
    u = diff / np.maximum(dist, 1e-9)[..., None]
    h = u[:, 1:] - u[:, :1]
    hth = np.einsum("bki,bkj->bij", h, h)
    det = hth[:, 0, 0] * hth[:, 1, 1] - hth[:, 0, 1] ** 2
    ok = det > 1e-12 * np.maximum(np.trace(hth, axis1=1, axis2=2) ** 2, 1e-300)
    inv = np.empty_like(hth)
    inv[:, 0, 0], inv[:, 1, 1] = hth[:, 1, 1], hth[:, 0, 0]
    inv[:, 0, 1] = inv[:, 1, 0] = -hth[:, 0, 1]
    inv = inv / np.where(ok, det, 1.0)[:, None, None]
    inv = inv / (np.trace(inv, axis1=1, axis2=2) / 2)[:, None, None]
    ok &= np.isfinite(inv).all(axis=(1, 2)) & np.isfinite(np.asarray(position_m, dtype=float)).all(axis=1)
    return np.where(ok[:, None, None], inv, np.eye(2))


def mahalanobis(error_vector_m: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """(B,) √(dᵀS⁻¹d) for error vectors d (B, 2) and shape matrices S (B, 2, 2), in m."""
    solved = np.linalg.solve(shape, error_vector_m[..., None])[..., 0]
    return np.sqrt(np.maximum((error_vector_m * solved).sum(-1), 0.0))


def ellipse_axes(shape: np.ndarray, scale_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Semi-major and semi-minor axes (m) and the major axis' angle (degrees counter-clockwise from east).

    Parameters
    ----------
    shape : numpy.ndarray
        (B, 2, 2) shape matrices.
    scale_m : numpy.ndarray
        (B,) the Mahalanobis radius q̂ ê of each ellipse, m.
    """
    values, vectors = np.linalg.eigh(shape)  # ascending
    major = vectors[:, :, 1]
    angle = np.degrees(np.arctan2(major[:, 1], major[:, 0])) % 180.0
    return scale_m * np.sqrt(values[:, 1]), scale_m * np.sqrt(values[:, 0]), angle


def inside_ellipse(error_vector_m: np.ndarray, a_m: np.ndarray, b_m: np.ndarray, angle_deg: np.ndarray) -> np.ndarray:
    """(B,) bool: the error vectors (estimate − truth) lie inside the ellipses (a, b, angle) centred on the estimates.

    A non-finite error vector (a failed event) is never inside; a degenerate ellipse (a zero axis) holds nothing
    off its axis.
    """
    finite = np.isfinite(error_vector_m).all(axis=1)
    error = np.where(finite[:, None], error_vector_m, 0.0)
    theta = np.radians(angle_deg)
    along = error[:, 0] * np.cos(theta) + error[:, 1] * np.sin(theta)
    across = -error[:, 0] * np.sin(theta) + error[:, 1] * np.cos(theta)
    with np.errstate(divide="ignore", invalid="ignore"):
        return finite & ((along / a_m) ** 2 + (across / b_m) ** 2 <= 1.0)
