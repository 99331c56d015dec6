"""A recorder's clock error at a given time: its offset plus its drift times the time elapsed.

A calibration states each recorder's clock offset at ``drift_origin_s`` (the first playback's time,
on the detections' clock) and its drift in s per s. A call is corrected by the clock error at its
own time; a call that carries no time (NaN) is taken at the origin, so it gets the offsets alone:
without a time, drift cannot be applied, and the offsets are what the playbacks measured.
"""

from __future__ import annotations

import numpy as np


def seconds_since_origin(time_s: np.ndarray, origin_s: float) -> np.ndarray:
    """(N,) each call's time after the drift origin, s (0 for a call without a time)."""
    return np.nan_to_num(np.asarray(time_s, dtype=float) - float(origin_s))


def clock_errors_s(offset_s: np.ndarray, drift: np.ndarray, origin_s: float, time_s: np.ndarray) -> np.ndarray:
    """(N, M) each recorder's clock error at each call's ``time_s`` ((N,), s): ``offset_s`` ((M,), s) at
    ``origin_s`` plus ``drift`` ((M,), s per s) times the time since."""
    elapsed = seconds_since_origin(time_s, origin_s)
    return np.asarray(offset_s, dtype=float)[None, :] + np.asarray(drift, dtype=float)[None, :] * elapsed[:, None]
