"""What ``calibrate`` refuses to fit, and what it leaves out: checks of the playbacks before and after the fit.

A calibration is written only from what the playbacks determine. Spots given in another frame
than the mics (UTM eastings beside a local frame), positions half given, a recorder that never
heard the playbacks, or windows holding only noise would otherwise move the mics by metres and
write a file that ``localize`` applies without a word.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import DataError
from acoustlab.core.types import Site
from acoustlab.toolkit.array_calibration import ArrayCalibration

log = logging.getLogger(__name__)

#: A time difference fits the calibrated array when its residual is within this, s: a direct path's pick fits to tens of
#: µs after calibration, a pick of noise or of another sound misses by milliseconds.
FIT_WITHIN_S = 5e-4
#: A recorder whose time differences miss the calibrated array (``FIT_WITHIN_S``) on more than this share of its pairs did
#: not hear the playbacks.
UNHEARD_SHARE = 0.5
#: A spot farther from the array's centre than this many times the array's extent (at least 100 m) is in another frame.
FAR_SPOT_EXTENTS = 10.0


def check_positions(events: pd.DataFrame, site: Site) -> None:
    """Refuse, in one line, playback positions half given, or so far from the array that they are in another frame.

    Raises
    ------
    DataError
        Naming the events (half given) or the spot and its distance (another frame).
    """
    xy = events[[col.TRUE_X, col.TRUE_Y]].to_numpy(float)
    half = np.isfinite(xy).sum(axis=1) == 1
    if half.any():
        ids = events[col.EVENT_ID].to_numpy()[half][:5].tolist()
        raise DataError(
            f"calibrate: {int(half.sum())} event(s) give only one of {col.TRUE_X}, {col.TRUE_Y} (event ids {ids}): a playback needs "
            "both, a call neither; complete or clear them"
        )
    mics = site.mic_positions_m[:, :2]
    centre = mics.mean(axis=0)
    reach = FAR_SPOT_EXTENTS * max(float(np.ptp(mics, axis=0).max()), 10.0)
    distance = np.hypot(*(xy - centre).T)
    far = np.isfinite(distance) & (distance > reach)
    if far.any():
        k = int(np.flatnonzero(far)[np.argmax(distance[far])])
        spot = events[col.POSITION_ID].iloc[k] if col.POSITION_ID in events else k
        raise DataError(
            f"calibrate: spot {spot} at ({xy[k, 0]:.1f}, {xy[k, 1]:.1f}) m lies {distance[k] / 1000:,.1f} km from the array's centre "
            f"({centre[0]:.1f}, {centre[1]:.1f}): the spots and the mics are in different frames (e.g. UTM and a local one); "
            "give both in one"
        )


def fit_shares(calibration: ArrayCalibration, n_mics: int) -> np.ndarray:
    """(M,) per recorder, the share of its playbacks' time differences that miss the calibrated array by more than
    ``FIT_WITHIN_S`` (NaN for a recorder with none)."""
    residual = np.abs(calibration.residual_after_s)
    shares = np.full(n_mics, np.nan)
    for m in range(n_mics):
        columns = [k for k, pair in enumerate(calibration.pairs) if m in pair]
        values = residual[:, columns]
        values = values[np.isfinite(values)]
        if values.size:
            shares[m] = float(np.mean(values > FIT_WITHIN_S))
    return shares


def unheard_mics(calibration: ArrayCalibration, mic_ids: list[str]) -> list[int]:
    """The recorders that did not hear the playbacks (``UNHEARD_SHARE``; one left out already, without pairs, is not listed).

    Raises
    ------
    DataError
        When fewer than 3 recorders heard them: the playbacks determine no array (noise-only
        windows, clips not of the playbacks, or the wrong spots); nothing is written.
    """
    shares = fit_shares(calibration, len(mic_ids))
    unheard = [int(m) for m in np.flatnonzero(shares > UNHEARD_SHARE)]  # NaN: a recorder already left out
    if int(np.sum(shares <= UNHEARD_SHARE)) < 3:
        residual = np.abs(calibration.residual_after_s[np.isfinite(calibration.residual_after_s)])
        raise DataError(
            f"calibrate: the playbacks' time differences fit no array ({np.mean(residual > FIT_WITHIN_S):.0%} of them miss it "
            f"by more than {1e3 * FIT_WITHIN_S:g} ms, median {1e3 * np.median(residual) if residual.size else float('nan'):.3g} ms): "
            "the windows hold noise or another sound, or the spots are wrong; nothing written"
        )
    if unheard:
        log.warning(
            "calibrate: recorder(s) %s did not hear the playbacks (%s of their time differences miss the array by more than "
            "%g ms, the others' at most %.0f%%): left out, kept at their stated positions and clocks",
            ", ".join(mic_ids[m] for m in unheard),
            ", ".join(f"{shares[m]:.0%}" for m in unheard),
            1e3 * FIT_WITHIN_S,
            100 * np.nanmax(np.delete(shares, unheard)),
        )
    return unheard


def without_mics(features: pd.DataFrame, site: Site, mics: list[int]) -> pd.DataFrame:
    """Features with every GCC candidate of the pairs that hold one of ``mics`` blanked (NaN): those pairs are left out."""
    features = features.copy()
    for i, j in site.mic_pairs:
        if i in mics or j in mics:
            k = 1
            while col.tdoa_lag(i, j, k) in features:
                features[col.tdoa_lag(i, j, k)] = np.nan
                k += 1
    return features


def with_unknown_uncertainty_from_one_spot(calibration: ArrayCalibration) -> ArrayCalibration:
    """From one spot the posterior, counting its pairs as independent, is thousands of times too small (a clock's σ in
    microseconds where it is unknown): the calibration's covariance becomes its priors' (what was stated; the estimates
    stay), said in ``not_identified`` and one warning. Calibrations from more spots are returned as they are."""
    if calibration.n_spots > 1:
        return calibration
    log.warning(
        "calibrate: one spot cannot tell what its estimates leave uncertain; the radii carry the stated (prior) "
        "uncertainties instead: play back from more spots (docs/calibrate.md)"
    )
    notes = {**calibration.not_identified, "uncertainty": "one spot: the estimates' uncertainty is unknown, the priors' is carried"}
    return dataclasses.replace(calibration, covariance=np.diag(np.asarray(calibration.prior_sd, dtype=float) ** 2), not_identified=notes)
