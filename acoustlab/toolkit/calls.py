"""Dry calls for simulation: shipped real recordings segmented into single calls, and synthetic calls.

Real recordings (``acoustlab/data/calls/catalog.csv``) are cut into single calls by onset
detection on the band-passed Hilbert envelope, trimmed, faded and peak-normalised. The parametric
generator makes FM sweeps, trills and harmonic stacks of varied bandwidth and duration; its calls
are labelled ``synthetic:<kind>``. CC BY-SA recordings are only used when asked for
(``include_share_alike``): anything rendered from them is CC BY-SA 4.0 too.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pandas as pd
import scipy.signal as ss

from acoustlab.core.errors import ConfigError, DataError
from acoustlab.core.resources import PACKAGE_DATA
from acoustlab.toolkit.audio import load_mono

CATALOG = PACKAGE_DATA / "calls" / "catalog.csv"
SYNTHETIC = "synthetic"
MIN_CALL_S = 0.01
SYNTHETIC_KINDS = ("fm_sweep", "trill", "harmonic_stack")


@dataclass(frozen=True)
class Call:
    """One dry call.

    Attributes
    ----------
    label : str
        ``<species>:<file>#<k>`` for a real call, ``synthetic:<kind>`` for a generated one.
    signal : numpy.ndarray
        (S,) samples with unit peak.
    licence : str
        Licence of the source recording (``generated`` for synthetic calls).
    """

    label: str
    signal: np.ndarray
    licence: str


def catalog() -> pd.DataFrame:
    """The shipped call recordings with species, band, pool and licence."""
    return pd.read_csv(CATALOG)


def segment_calls(
    signal: np.ndarray,
    sample_rate_hz: float,
    band_hz: tuple[float, float],
    threshold_db: float = 12.0,
    min_duration_s: float = 0.03,
    max_duration_s: float = 0.5,
    min_gap_s: float = 0.04,
    pad_s: float = 0.01,
    fade_s: float = 0.005,
) -> list[np.ndarray]:
    """Cut a recording into single calls.

    Band-pass (4th-order Butterworth, zero phase), Hilbert envelope smoothed over 5 ms, in dB;
    a call is a run above (noise floor + ``threshold_db``), where the floor is the 20th percentile
    of the envelope; runs closer than ``min_gap_s`` merge; runs shorter than ``min_duration_s`` are
    dropped and longer than ``max_duration_s`` are cut. Each call is padded, faded with raised-cosine
    ramps and peak-normalised.

    Parameters
    ----------
    signal : numpy.ndarray
        (S,) mono recording.
    sample_rate_hz : float
        Sampling rate in Hz.
    band_hz : tuple of float
        (low, high) band of the species in Hz.

    Returns
    -------
    list of numpy.ndarray
        The calls (float64, unit peak), in time order.
    """
    nyq = sample_rate_hz / 2
    low, high = band_hz
    if high >= nyq:
        high = 0.95 * nyq
    if not 0 < low < high:
        raise DataError(f"cannot band-pass calls to {band_hz} Hz at a sample rate of {sample_rate_hz} Hz")
    sos = ss.butter(4, [low / nyq, high / nyq], btype="bandpass", output="sos")
    x = ss.sosfiltfilt(sos, np.asarray(signal, dtype=float))
    env = np.abs(ss.hilbert(x))
    win = max(int(0.005 * sample_rate_hz), 1)
    env = np.convolve(env, np.ones(win) / win, mode="same")
    env_db = 20 * np.log10(np.maximum(env, 1e-12))
    active = env_db > np.percentile(env_db, 20) + threshold_db
    edges = np.flatnonzero(np.diff(np.concatenate([[0], active.astype(int), [0]])))
    runs = list(zip(edges[::2], edges[1::2]))
    merged: list[list[int]] = []
    for start, stop in runs:
        if merged and start - merged[-1][1] < min_gap_s * sample_rate_hz:
            merged[-1][1] = stop
        else:
            merged.append([start, stop])
    pad, fade = int(pad_s * sample_rate_hz), max(int(fade_s * sample_rate_hz), 1)
    calls = []
    for start, stop in merged:
        if stop - start < min_duration_s * sample_rate_hz:
            continue
        stop = min(stop, start + int(max_duration_s * sample_rate_hz))
        seg = x[max(start - pad, 0) : min(stop + pad, x.size)].copy()
        ramp = 0.5 - 0.5 * np.cos(np.linspace(0, np.pi, fade))
        seg[:fade] *= ramp
        seg[-fade:] *= ramp[::-1]
        calls.append(seg / np.max(np.abs(seg)))
    return calls


@lru_cache(maxsize=64)
def _segments(file: str, sample_rate_hz: float, band: tuple[float, float]) -> tuple[np.ndarray, ...]:
    rec = load_mono(f"acoustlab://calls/{file}", sample_rate_hz)
    return tuple(segment_calls(rec, sample_rate_hz, band))


def tapered_chirp(f_start_hz: float, f_end_hz: float, duration_s: float, sample_rate_hz: float, method: str = "linear") -> np.ndarray:
    """A frequency-modulated sweep with 20 % Tukey tapers (peak at most 1): the free-field simulator's calls, the playback sweep.

    Parameters
    ----------
    f_start_hz, f_end_hz : float
        Start and end frequencies in Hz.
    duration_s : float
        Duration in s.
    sample_rate_hz : float
        Sampling rate in Hz.
    method : str
        Any method of ``scipy.signal.chirp`` (``linear``, ``logarithmic``, ``quadratic``…).

    Returns
    -------
    numpy.ndarray
        (round(duration_s × sample_rate_hz),) float64 samples.
    """
    t = np.arange(int(round(duration_s * sample_rate_hz))) / sample_rate_hz
    sweep = ss.chirp(t, f0=f_start_hz, t1=duration_s, f1=f_end_hz, method=method)
    return sweep * ss.windows.tukey(t.size, alpha=0.2)


def synthetic_call(rng: np.random.Generator, sample_rate_hz: float, kind: str | None = None) -> tuple[str, np.ndarray]:
    """A parametric synthetic call: FM sweep, trill or harmonic stack, with random parameters.

    Frequencies stay between 1 kHz and min(9 kHz, 0.4 × sample rate); durations 50–450 ms.

    Returns
    -------
    label : str
        ``synthetic:<kind>``.
    signal : numpy.ndarray
        (S,) unit-peak samples.
    """
    kind = kind or SYNTHETIC_KINDS[int(rng.integers(len(SYNTHETIC_KINDS)))]
    f_top = min(9000.0, 0.4 * sample_rate_hz)
    if kind == "fm_sweep":
        dur = rng.uniform(0.05, 0.35)
        f0, f1 = rng.uniform(1000, f_top, size=2)
        t = np.arange(int(dur * sample_rate_hz)) / sample_rate_hz
        x = ss.chirp(t, f0=f0, t1=dur, f1=f1, method=["linear", "logarithmic", "quadratic"][int(rng.integers(3))])
    elif kind == "trill":
        n_notes = int(rng.integers(4, 15))
        note = rng.uniform(0.015, 0.04)
        gap = rng.uniform(0.005, 0.03)
        n_notes = min(n_notes, int(0.45 / (note + gap)))
        f0 = rng.uniform(1500, f_top * 0.8)
        f1 = np.clip(f0 * rng.uniform(0.6, 1.6), 1000, f_top)
        t = np.arange(int(note * sample_rate_hz)) / sample_rate_hz
        one = ss.chirp(t, f0=f0, t1=note, f1=f1) * ss.windows.hann(t.size)
        x = np.concatenate([np.concatenate([one, np.zeros(int(gap * sample_rate_hz))]) for _ in range(n_notes)])
    elif kind == "harmonic_stack":
        dur = rng.uniform(0.08, 0.4)
        f0 = rng.uniform(1000, f_top / 3)
        t = np.arange(int(dur * sample_rate_hz)) / sample_rate_hz
        vib = 1 + 0.03 * np.sin(2 * np.pi * rng.uniform(5, 30) * t)
        phase = 2 * np.pi * np.cumsum(f0 * vib) / sample_rate_hz
        x = sum((0.6**h) * np.sin((h + 1) * phase) for h in range(int(rng.integers(2, 5))) if (h + 1) * f0 < f_top)
    else:
        raise ConfigError(f"synthetic call kind must be one of {SYNTHETIC_KINDS}; got {kind!r}")
    x = x * ss.windows.tukey(x.size, alpha=0.2)
    return f"synthetic:{kind}", x / np.max(np.abs(x))


class CallPool:
    """The calls a site's simulations draw from: its species' real calls plus synthetic ones.

    Parameters
    ----------
    species : sequence of str
        Species names from the catalog, and/or ``synthetic``.
    sample_rate_hz : float
        Sampling rate in Hz.
    include_share_alike : bool
        Also use CC BY-SA recordings (renders derived from them are CC BY-SA 4.0).
    synthetic_fraction : float
        Probability of drawing a synthetic call when the pool has real calls too.
    """

    def __init__(self, species, sample_rate_hz: float, include_share_alike: bool = False, synthetic_fraction: float = 0.3) -> None:
        self.sample_rate_hz = float(sample_rate_hz)
        table = catalog()
        if not include_share_alike:
            table = table[table["pool"] == "permissive"]
        species = [str(s) for s in species]
        unknown = [s for s in species if s != SYNTHETIC and s not in set(catalog()["species"])]
        if unknown:
            raise ConfigError(f"unknown species {unknown} in the call pool; known: {sorted(set(catalog()['species']))} or 'synthetic'")
        self.synthetic = SYNTHETIC in species
        self.real: list[Call] = []
        for row in table[table["species"].isin(species)].itertuples():
            for k, seg in enumerate(_segments(row.file, self.sample_rate_hz, (float(row.band_low_hz), float(row.band_high_hz)))):
                if seg.size >= MIN_CALL_S * self.sample_rate_hz:
                    self.real.append(Call(f"{row.species}:{row.file}#{k}", seg, row.licence))
        if not self.real and not self.synthetic:
            raise ConfigError(
                f"the call pool for species {species} is empty"
                + ("" if include_share_alike else " (CC BY-SA species need include_share_alike=true)")
            )
        self.synthetic_fraction = float(synthetic_fraction) if self.real else 1.0
        if not self.synthetic:
            self.synthetic_fraction = 0.0

    def __len__(self) -> int:
        return len(self.real) + (1 if self.synthetic else 0)

    def draw(self, rng: np.random.Generator) -> Call:
        """One call: synthetic with probability ``synthetic_fraction``, else a uniformly drawn real call."""
        if rng.random() < self.synthetic_fraction:
            label, sig = synthetic_call(rng, self.sample_rate_hz)
            return Call(label, sig, "generated")
        return self.real[int(rng.integers(len(self.real)))]

    @property
    def max_duration_s(self) -> float:
        """Longest call in the pool, in s (synthetic calls are at most 0.45 s)."""
        real = max((c.signal.size for c in self.real), default=0) / self.sample_rate_hz
        return max(real, 0.45 if self.synthetic else 0.0)
