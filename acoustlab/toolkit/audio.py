"""Reading audio files (soundfile) and resampling (scipy.signal.resample_poly)."""

from __future__ import annotations

from fractions import Fraction
from functools import lru_cache

import numpy as np
import scipy.signal as ss
import soundfile as sf

from acoustlab.core.errors import DataError
from acoustlab.core.resources import resolve_path


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
    path = resolve_path(path_text)
    try:
        data, rate = sf.read(str(path), dtype="float32", always_2d=True)
    except Exception as exc:  # soundfile raises RuntimeError/LibsndfileError/OSError
        raise DataError(f"cannot read audio file {path}: {exc}") from None
    mono = data.mean(axis=1)
    if rate != sample_rate_hz:
        ratio = Fraction(float(sample_rate_hz) / float(rate)).limit_denominator(1000)
        mono = ss.resample_poly(mono, ratio.numerator, ratio.denominator).astype(np.float32)
    mono.setflags(write=False)
    return mono
