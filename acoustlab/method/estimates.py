"""What predicting and fitting share: a split's test-time estimates and the per-event geometry helpers.

Used by ``acoustlab.method.pipeline`` (fitting) and ``acoustlab.method.fitted`` (predicting).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.types import Site
from acoustlab.method.trust import (
    SupportCues,
    TrainingSupport,
    TrustedDecision,
)
from acoustlab.toolkit.event_physics import event_speed_of_sound_m_s
from acoustlab.toolkit.geometry import distance_to_polygon_m, position_crb_m, source_region


def crb_from_features(features: pd.DataFrame, events: pd.DataFrame, site: Site) -> np.ndarray | None:
    """Per-event Cramér–Rao bound on position (m) at the true position, from measured signal features.

    Uses the median over mics of the per-mic SNR, RMS bandwidth √(centroid² + bandwidth²), band
    2 × bandwidth and the envelope spread as observation time; None when those features are absent.
    """
    m = site.n_mics
    per_mic = (col.snr_db, col.spectral_centroid_hz, col.spectral_bandwidth_hz, col.ir_spread_s)
    if not all(name(k) in features.columns for name in per_mic for k in range(m)) or events[[col.TRUE_X, col.TRUE_Y]].isna().any().any():
        return None

    def med(name: Callable[[int], str]) -> np.ndarray:
        return np.median(features[[name(k) for k in range(m)]].to_numpy(float), axis=1)

    centroid, bandwidth = med(col.spectral_centroid_hz), med(col.spectral_bandwidth_hz)
    c = event_speed_of_sound_m_s(events)
    return position_crb_m(
        site.mic_positions_m,
        events[[col.TRUE_X, col.TRUE_Y, col.TRUE_Z]].to_numpy(float),
        med(col.snr_db),
        np.sqrt(centroid**2 + bandwidth**2),
        med(col.ir_spread_s),
        2 * bandwidth,
        c,
    )


def error_2d_m(estimate_m: np.ndarray, truth_m: np.ndarray) -> np.ndarray:
    """Euclidean 2-D error in m (inf where the estimate is not finite)."""
    err = np.sqrt(((np.asarray(estimate_m) - np.asarray(truth_m)[:, :2]) ** 2).sum(axis=1))
    return np.where(np.isfinite(err), err, np.inf)


def hull_distance_extent(site: Site, position_m: np.ndarray) -> np.ndarray:
    """(B,) each position's distance outside the mics' hull in units of the array extent (0 inside; NaN without a position)."""
    polygon, extent = source_region(site.mic_positions_m, 1.0)
    distance = distance_to_polygon_m(np.nan_to_num(position_m[:, :2]), polygon) / extent
    return np.where(np.isfinite(position_m[:, :2]).all(axis=1), distance, np.nan)


@dataclass
class TestEstimates:
    """The test events' estimates and the error model's inputs for them."""

    #: (test, 2) the final point model's estimates, m
    model_xy: np.ndarray
    support: TrainingSupport | None
    #: the test rows checked against the support (shared by the configured and the extra gates)
    cues: SupportCues
    trusted: TrustedDecision
    #: (test,) GDOP at the reported estimate
    gdop: np.ndarray
    x_error: pd.DataFrame
