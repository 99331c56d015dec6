"""The highest local maxima of a correlation window in one pass (compiled with numba), for the GCC's coarse search.

``acoustlab.toolkit.gcc_coarse`` refines, per pair window, the M highest local maxima of the
correlation and the M highest local maxima of its two-sample sums, and reports the window's RMS.
In numpy that takes some 25 passes over the window (the two peak masks, a masked copy for each,
two ``argpartition`` selections, a double-precision square for the RMS), a large share of a coarse
event's time. ``window_peaks`` does it in one pass per row, keeping the M best of each kind in
a small sorted buffer.

Written by hand because no library selects the top-M local maxima of a sequence without
materialising the peak mask and a masked copy (``scipy.signal.find_peaks`` treats plateaus
differently and returns every peak; ``numpy.argpartition`` needs the masked copy). The peak rule is
``acoustlab.toolkit.dsp.local_maxima``'s (≥ the left neighbour, > the right one, edges allowed);
ties are resolved deterministically: higher value first, the lower index first among equal values.

This module imports numba; ``acoustlab.toolkit.gcc_coarse`` imports it on its first coarse search
only. The compiled kernel is cached beside this module (``cache=True``): it compiles once per
installation.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np


class WindowPeaks(NamedTuple):
    """What ``window_peaks`` finds in each row of a window (E rows).

    Attributes
    ----------
    top : numpy.ndarray
        (E, m) indices of the highest local maxima, highest first (ties: lower index first); only
        the first ``n_top`` of a row are peaks, the rest are 0.
    n_top : numpy.ndarray
        (E,) how many local maxima ``top`` holds per row (≤ m).
    top_sum : numpy.ndarray
        (E, m_sum) indices i of the highest local maxima of the sums values[i] + values[i + 1],
        ordered likewise; the first ``n_sum`` of a row are peaks.
    n_sum : numpy.ndarray
        (E,) how many sum maxima ``top_sum`` holds per row (≤ m_sum).
    sum_of_squares : numpy.ndarray
        (E,) Σ values², accumulated in double precision.
    """

    top: np.ndarray
    n_top: np.ndarray
    top_sum: np.ndarray
    n_sum: np.ndarray
    sum_of_squares: np.ndarray


def window_peaks(values: np.ndarray, m: int, m_sum: int) -> WindowPeaks:
    """The m highest local maxima of every row of ``values`` (E, L), the m_sum highest of its two-sample sums, and Σ values².

    Parameters
    ----------
    values : numpy.ndarray
        (E, L) float32 or float64 rows (a strided view is fine); NaN and −inf are never peaks, nor is a sample next to NaN.
    m, m_sum : int
        How many maxima to keep of each kind (≥ 0).

    Returns
    -------
    WindowPeaks
        See its attributes.
    """
    values = np.asarray(values)
    if values.ndim != 2 or values.dtype not in (np.float32, np.float64):
        raise ValueError(f"window_peaks needs a 2-D float32 or float64 array; got shape {values.shape}, dtype {values.dtype}")
    if m < 0 or m_sum < 0:
        raise ValueError(f"window_peaks needs m, m_sum >= 0; got {m}, {m_sum}")
    return WindowPeaks(*_kernel(values, int(m), int(m_sum)))


@numba.njit(cache=True, nogil=True, inline="always")
def _insert(vals, idxs, count, m, v, i):
    # vals[:count] descending; v goes after every value >= v (i exceeds every kept index: ties keep the lower index)
    pos = count if count < m else m - 1
    while pos > 0 and v > vals[pos - 1]:
        vals[pos] = vals[pos - 1]
        idxs[pos] = idxs[pos - 1]
        pos -= 1
    vals[pos] = v
    idxs[pos] = i
    return count + 1 if count < m else m


@numba.njit(cache=True, nogil=True)
def _kernel(values, m, m_sum):
    e, n = values.shape
    top, n_top = np.zeros((e, m), np.int64), np.zeros(e, np.int64)
    top_sum, n_sum = np.zeros((e, m_sum), np.int64), np.zeros(e, np.int64)
    sum_of_squares = np.zeros(e, np.float64)
    kept, kept_sum = np.empty(m, values.dtype), np.empty(m_sum, values.dtype)
    for r in range(e):
        row = values[r]
        # four accumulators: the additions' latency overlaps (one would take 4 cycles a sample)
        a0 = a1 = a2 = a3 = 0.0
        i = 0
        while i + 4 <= n:
            x0, x1, x2, x3 = np.float64(row[i]), np.float64(row[i + 1]), np.float64(row[i + 2]), np.float64(row[i + 3])
            a0 += x0 * x0
            a1 += x1 * x1
            a2 += x2 * x2
            a3 += x3 * x3
            i += 4
        while i < n:
            x0 = np.float64(row[i])
            a0 += x0 * x0
            i += 1
        sum_of_squares[r] = (a0 + a1) + (a2 + a3)
        count = count_sum = 0
        floor = floor_sum = -np.inf  # the m-th kept value once m are kept (the peak test runs only above it); never NaN or -inf
        for i in range(n):
            v = row[i]
            if m > 0 and v > floor and (i == 0 or v >= row[i - 1]) and (i == n - 1 or v > row[i + 1]):
                count = _insert(kept, top[r], count, m, v, i)
                if count == m:
                    floor = kept[m - 1]
            if m_sum > 0 and i < n - 1:
                s = row[i] + row[i + 1]
                if s > floor_sum and (i == 0 or s >= row[i - 1] + row[i]) and (i == n - 2 or s > row[i + 1] + row[i + 2]):
                    count_sum = _insert(kept_sum, top_sum[r], count_sum, m_sum, s, i)
                    if count_sum == m_sum:
                        floor_sum = kept_sum[m_sum - 1]
        n_top[r], n_sum[r] = count, count_sum
    return top, n_top, top_sum, n_sum, sum_of_squares
