"""Quality checks of recorded channels: what makes a clip unfit to localize from.

A field recorder fails in a handful of ways that all produce numbers a TDOA solver happily
turns into a position hundreds of metres away: a dead channel (digital zeros or a constant), a
file cut short (the event lies partly or wholly past its end, or before its start), non-finite
samples from a damaged file, and clipping. ``clip_quality`` names each of these per clip so
the caller can flag the event instead of localizing it from zeros. ``duplicate_channels``
finds mics whose clips are the same samples (one channel wired or listed twice): their TDOA is 0
whatever the source, and every fix collapses onto one point with a radius of 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from acoustlab.core import columns as col

#: Every reason a clip can be flagged for, in the order they are reported.
QUALITY_REASONS = ("out_of_range", "truncated", "nonfinite", "dead", "clipped", "duplicate", "weak_gcc")
#: An event whose flagged clips leave at least this many good mics is solved from those (the bad ones dropped): three
#: mics give a 2-D fix at the assumed height. With fewer the event is not placed.
MIN_GOOD_MICS = 3


def mics_to_drop(reasons_per_mic: list[list[str]] | np.ndarray) -> tuple[str, bool]:
    """The mics an event can do without, and whether it stays usable.

    A flagged clip (any of ``QUALITY_REASONS``) costs that mic, not the event: the event is solved
    from the other mics where at least ``MIN_GOOD_MICS`` remain.

    Returns
    -------
    dropped : str
        Indices of the flagged mics, ";"-separated ("" when every clip is fine, or too few remain).
    usable : bool
        True when no clip is flagged or enough good mics remain.
    """
    bad = [m for m, reasons in enumerate(reasons_per_mic) if reasons]
    if not bad:
        return "", True
    if len(reasons_per_mic) - len(bad) < MIN_GOOD_MICS:
        return "", False
    return ";".join(str(m) for m in bad), True


#: Events column: the mics whose clip was dead (``;``-separated indices), for ``failed_positions``.
DEAD_MICS = "dead_mics"


def failed_positions(events: pd.DataFrame) -> np.ndarray:
    """(E,) each event's ``hardware_failure``: as stated, or true where some mic is dead in every event of its position.

    A recorder dead for one call may have been masked by wind; dead for every call at a spot, it
    failed there. Needs all of a position's events at once (after reading them in chunks).
    """
    stated = events[col.HARDWARE_FAILURE].to_numpy(bool) if col.HARDWARE_FAILURE in events else np.zeros(len(events), bool)
    if DEAD_MICS not in events or len(events) == 0:
        return stated
    dead = events[DEAD_MICS].fillna("").astype(str)
    position = events[col.POSITION_ID].to_numpy()
    out = stated.copy()
    for pos in np.unique(position):
        rows = position == pos
        shared = set.intersection(*(set(filter(None, text.split(";"))) for text in dead[rows]))
        if shared:
            out[rows] = True
    return out


def weakly_correlated_mics(
    heights: np.ndarray, pairs: list[tuple[int, int]], n_mics: int, min_peak: float | None, relative: float | None = None
) -> np.ndarray:
    """(E, M) True where a mic's strongest GCC peak with any other mic is below ``min_peak``, or below ``relative`` times the
    event's strongest pair peak.

    A recorder that hears only its own noise (a wind-hit or covered microphone, a clock jump) has
    no clear peak with anyone, while each good mic keeps a clear peak with another good one; the
    maximum over a mic's pairs separates the two even when several mics are weak.

    Parameters
    ----------
    heights : numpy.ndarray
        (E, P) GCC height of each pair's strongest peak (dimensionless, 1 = a perfect match); NaN counts as no peak.
    pairs : list of (int, int)
        The P mic pairs, in the order of ``heights``' columns.
    n_mics : int
        Mics of the array.
    min_peak : float or None
        The height a mic needs with at least one other mic (None: no absolute height).
    relative : float or None
        The share of its event's strongest pair peak a mic's strongest peak needs (None: none). A
        GCC's height depends on the band, the call's length and the files' coding (an MP3 keeps
        less of the high band than a WAV), so one height does not hold across recordings; the
        event's own strongest pair sets the scale there.
    """
    heights = np.where(np.isfinite(heights), heights, -np.inf)
    best = np.full((heights.shape[0], n_mics), -np.inf)
    for p, (i, j) in enumerate(pairs):
        best[:, i] = np.maximum(best[:, i], heights[:, p])
        best[:, j] = np.maximum(best[:, j], heights[:, p])
    weak = np.zeros(best.shape, dtype=bool)
    if min_peak is not None:
        weak |= best < min_peak
    if relative is not None:
        weak |= best < relative * best.max(axis=1, keepdims=True)
    return weak


def dropped_mask(dropped: pd.Series | None, n_events: int, n_mics: int) -> np.ndarray:
    """(E, M) True where an event's mic is dropped (from a ``mics_dropped`` column; all False without one)."""
    mask = np.zeros((n_events, n_mics), dtype=bool)
    if dropped is None:
        return mask
    for e, text in enumerate(dropped.fillna("").astype(str)):
        for m in text.split(";"):
            if m.strip():
                mask[e, int(m)] = True
    return mask


@dataclass(frozen=True)
class QualityThresholds:
    """When a clip counts as dead or clipped.

    Attributes
    ----------
    dead_peak_to_peak : float
        A clip whose peak-to-peak amplitude is at most this (full scale = 1) is dead: digital
        zeros or a constant (1e-6 ≈ −120 dBFS, below any real microphone's self-noise).
    clip_level : float
        Absolute sample value (full scale = 1) at or above which a sample counts as clipped.
    clip_share : float
        A clip with more than this share of clipped samples is flagged as clipped.
    """

    dead_peak_to_peak: float = 1e-6
    clip_level: float = 0.99
    clip_share: float = 0.001


def clip_quality(
    signal: np.ndarray, start: int, length: int, thresholds: QualityThresholds, margin: int = 0, extension: int = 0
) -> tuple[np.ndarray, list[str]]:
    """Cut ``length`` samples from ``start`` (may be negative or past the end) and say what is wrong with them.

    Parameters
    ----------
    signal : numpy.ndarray
        (S,) the whole channel, full scale = 1.
    start : int
        First sample of the clip (negative: the clip begins before the recording).
    length : int
        Samples in the clip.
    thresholds : QualityThresholds
        When a clip is dead or clipped.
    margin : int
        Samples at either end that are context, not the event (padding): they may lie outside
        the recording without the clip counting as truncated.
    extension : int
        Samples at the end beyond the window, there to reach an FFT-friendly length
        (``acoustlab.toolkit.dsp.clip_samples``): zeros where the recording ends, never a flag.

    Returns
    -------
    clip : numpy.ndarray
        (length,) float32; samples outside the recording and non-finite samples are 0, the rest
        at their true offset (never shifted).
    reasons : list of str
        Members of ``QUALITY_REASONS`` that apply; empty for a good clip.
    """
    clip = np.zeros(length, dtype=np.float32)
    lo, hi = max(start, 0), min(start + length, signal.size)
    reasons: list[str] = []
    part = np.asarray(signal[lo:hi], dtype=np.float32)
    # the extremes answer most checks in two passes: NaN and ±inf show in them, and a clip whose extremes stay below
    # the clip level has no clipped sample (the per-sample checks run only where the extremes call for them)
    low, high = (part.min(), part.max()) if part.size else (np.float32(0), np.float32(0))
    all_finite = bool(np.isfinite(low) and np.isfinite(high))
    if not all_finite:
        part = np.where(np.isfinite(part), part, np.float32(0.0))
        low, high = part.min(), part.max()
    if hi > lo:
        clip[lo - start : hi - start] = part
    end = start + length - margin - extension  # where the event's own samples end
    if min(hi, end) <= max(lo, start + margin):
        return clip, ["out_of_range"]
    if lo > start + margin or hi < end:
        reasons.append("truncated")
    if not all_finite:
        reasons.append("nonfinite")
    if float(high - low) <= thresholds.dead_peak_to_peak:  # np.ptp's value
        reasons.append("dead")
    elif max(-float(low), float(high)) < thresholds.clip_level and thresholds.clip_share >= 0:
        pass  # no sample reaches the clip level
    elif float(np.mean(np.abs(part) >= thresholds.clip_level)) > thresholds.clip_share:
        reasons.append("clipped")
    return clip, reasons


def duplicate_channels(clips: np.ndarray, tolerance: float = 1e-7) -> list[int]:
    """Mics whose clip repeats an earlier mic's, sample for sample (dead clips excepted: they are flagged as dead).

    Parameters
    ----------
    clips : numpy.ndarray
        (M, S) one event's clips, full scale = 1.
    tolerance : float
        Largest absolute difference (full scale) still counted as the same samples.

    Returns
    -------
    list of int
        Indices of the later mic of every identical pair, each once.
    """
    live = [m for m in range(len(clips)) if float(np.ptp(clips[m])) > tolerance]
    out = []
    for k, m in enumerate(live):
        if any(float(np.max(np.abs(clips[m] - clips[j]))) <= tolerance for j in live[:k]):
            out.append(m)
    return out
