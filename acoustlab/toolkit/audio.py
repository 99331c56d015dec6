"""Reading audio files (soundfile) and resampling (scipy.signal.resample_poly)."""

from __future__ import annotations

from fractions import Fraction
from functools import lru_cache

import numpy as np
import scipy.signal as ss
import soundfile as sf

from acoustlab.core.errors import DataError
from acoustlab.core.resources import resolve_path


def _read(path_text: str) -> tuple[np.ndarray, float]:
    """(S, C) float32 samples and the file's rate; a ``DataError`` naming the file when it cannot be read."""
    path = resolve_path(path_text)
    try:
        data, rate = sf.read(str(path), dtype="float32", always_2d=True)
    except Exception as exc:  # soundfile raises RuntimeError/LibsndfileError/OSError
        raise DataError(f"cannot read audio file {path}: {exc}") from None
    return data, float(rate)


def _resample(x: np.ndarray, rate: float, sample_rate_hz: float) -> np.ndarray:
    """``x`` (resampled along axis 0 by polyphase filtering) at ``sample_rate_hz``, float32."""
    if rate == sample_rate_hz:
        return x
    ratio = Fraction(float(sample_rate_hz) / float(rate)).limit_denominator(1000)
    return ss.resample_poly(x, ratio.numerator, ratio.denominator, axis=0).astype(np.float32)


@lru_cache(maxsize=32)
def load_mono(path_text: str, sample_rate_hz: float) -> np.ndarray:
    """A mono float32 signal at ``sample_rate_hz`` (channels averaged, polyphase resampling).

    Parameters
    ----------
    path_text : str
        Path or ``acoustlab://`` URI of a WAV/FLAC file.
    sample_rate_hz : float
        Wanted sampling rate in Hz.

    Returns
    -------
    numpy.ndarray
        (S,) float32 samples; treat as read-only (cached).
    """
    data, rate = _read(path_text)
    mono = _resample(data.mean(axis=1), rate, sample_rate_hz)
    mono.setflags(write=False)
    return mono


@lru_cache(maxsize=2)
def load_channels(path_text: str, sample_rate_hz: float) -> np.ndarray:
    """Every channel of a multichannel file at ``sample_rate_hz`` (polyphase resampling), read once per file.

    Returns
    -------
    numpy.ndarray
        (C, S) float32 samples; treat as read-only (cached).
    """
    data, rate = _read(path_text)
    channels = np.ascontiguousarray(_resample(data, rate, sample_rate_hz).T, dtype=np.float32)
    channels.setflags(write=False)
    return channels
