"""A synthetic season for trying and benchmarking season-scale localization: long files, real file layout.

Calls (frequency-modulated sweeps with harmonics, like many songbird elements) are placed at
random points over the array and rendered into every recorder's long noise recording with the
free-field delay (distance over the speed of sound, fractional delays through an FFT phase ramp)
and spherical spreading; files are cut at fixed lengths and named by their start time
(``<recorder>/YYYYMMDD_HHMMSS.wav``, 16-bit), so calls cross file boundaries wherever they fall.
A Raven selection table per recorder lists the calls with ``Begin File``, ``File Offset (s)`` and
the call's band. This is a check of the season machinery, not of the propagation physics (the
project's simulator is for that): the truth is known exactly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import soundfile as sf

from acoustlab.core import columns as col
from acoustlab.core.types import Site
from acoustlab.toolkit.dsp import coloured_noise, delay_and_scale
from acoustlab.toolkit.physics import speed_of_sound_m_s

log = logging.getLogger(__name__)


@dataclass
class SyntheticSeason:
    """Settings of a synthetic season.

    Attributes
    ----------
    mics_m : numpy.ndarray
        (M, 3) recorder positions, m.
    duration_s : float
        Length of the season, s.
    file_s : float
        Length of each file, s.
    n_calls : int
        Calls placed uniformly in time (at least ``min_spacing_s`` apart).
    sample_rate_hz : float
        Sample rate of the files, Hz.
    snr_db : (float, float)
        Range of the call's SNR at the nearest recorder, dB.
    source_margin_m : float
        Sources are drawn in the mics' bounding box grown by this margin, m.
    speed_of_sound_m_s : float
        Sound speed used to render, m/s.
    seed : int
        Seed of every random draw.
    origin : str
        Wall-clock start of the season (ISO 8601).
    singer_m : (float, float, float), optional
        One bird singing from this spot (x, y, z in m) for the whole season; None: each call at a random spot.
    """

    mics_m: np.ndarray
    duration_s: float = 600.0
    file_s: float = 120.0
    n_calls: int = 200
    sample_rate_hz: float = 24000.0
    snr_db: tuple[float, float] = (15.0, 30.0)
    source_margin_m: float = 0.0
    source_height_m: tuple[float, float] = (1.0, 10.0)
    speed_of_sound_m_s: float = 343.0
    min_spacing_s: float = 1.0
    seed: int = 0
    origin: str = "2026-05-01T05:00:00"
    singer_m: tuple[float, float, float] | None = None

    @classmethod
    def for_site(cls, site: Site, **settings: Any) -> SyntheticSeason:
        """A season of ``site``: its mics, its source heights, sound at the middle of its weather ranges (what a season run assumes)."""
        speed = speed_of_sound_m_s(float(np.mean(site.temperature_range_c)), float(np.mean(site.relative_humidity_range_pct)))
        return cls(
            mics_m=site.mic_positions_m, source_height_m=tuple(site.source_height_range_m), speed_of_sound_m_s=float(speed), **settings
        )


def _call(rng: np.random.Generator, sample_rate_hz: float) -> tuple[np.ndarray, float, float]:
    """A frequency-modulated sweep with two harmonics and a raised-cosine envelope; returns (signal, low Hz, high Hz)."""
    duration = rng.uniform(0.15, 0.4)
    t = np.arange(int(duration * sample_rate_hz)) / sample_rate_hz
    f0, f1 = rng.uniform(2000, 4000), rng.uniform(3000, 5500)
    phase = 2 * np.pi * (f0 * t + (f1 - f0) * t**2 / (2 * duration))
    signal = np.sin(phase) + 0.4 * np.sin(2 * phase)
    signal *= 0.5 - 0.5 * np.cos(2 * np.pi * t / duration)
    return signal / np.sqrt(np.mean(signal**2)), min(f0, f1), 2 * max(f0, f1)


def write_season(settings: SyntheticSeason, directory: Path) -> pd.DataFrame:
    """Write the recordings and Raven tables of a synthetic season under ``directory``; return the calls' truth.

    Layout: ``directory/audio/R<k>/YYYYMMDD_HHMMSS.wav`` and ``directory/raven/R<k>.Table.1.selections.txt``.

    Returns
    -------
    pandas.DataFrame
        One row per call: ``call_id, emission_s`` (season seconds), ``x_m, y_m, z_m``, ``low_hz, high_hz``.
    """
    s = settings
    rng = np.random.default_rng(s.seed)
    mics = np.asarray(s.mics_m, float)
    fs = s.sample_rate_hz
    lo, hi = mics[:, :2].min(0) - s.source_margin_m, mics[:, :2].max(0) + s.source_margin_m
    slots = np.sort(rng.choice(int((s.duration_s - 2) / s.min_spacing_s), size=s.n_calls, replace=False))
    emission = 0.5 + slots * s.min_spacing_s + rng.uniform(0, 0.2, s.n_calls)
    xy = rng.uniform(lo, hi, size=(s.n_calls, 2))
    z = rng.uniform(*s.source_height_m, size=s.n_calls)
    if s.singer_m is not None:  # one bird on one perch all season
        xy, z = np.tile(np.asarray(s.singer_m[:2], float), (s.n_calls, 1)), np.full(s.n_calls, float(s.singer_m[2]))
    drawn = [_call(rng, fs) for _ in range(s.n_calls)]
    calls, bands = [d[0] for d in drawn], [(d[1], d[2]) for d in drawn]
    dist = np.sqrt(((xy[:, None, :] - mics[None, :, :2]) ** 2).sum(-1) + (z[:, None] - mics[None, :, 2]) ** 2)
    arrival = emission[:, None] + dist / s.speed_of_sound_m_s
    snr = rng.uniform(*s.snr_db, size=s.n_calls)
    noise_rms = 0.01
    gain = noise_rms * 10 ** (snr / 20)[:, None] * dist.min(axis=1, keepdims=True) / dist  # 1/r, the nearest at the drawn SNR
    origin = pd.Timestamp(s.origin)
    n_files = int(np.ceil(s.duration_s / s.file_s))
    n_file = int(round(s.file_s * fs))
    names = [f"{(origin + pd.Timedelta(seconds=k * s.file_s)):%Y%m%d_%H%M%S}.wav" for k in range(n_files)]
    for m in range(len(mics)):
        folder = directory / "audio" / f"R{m}"
        folder.mkdir(parents=True, exist_ok=True)
        for k in range(n_files):
            t0 = k * n_file  # first sample of the file on the season's sample grid
            audio = noise_rms * coloured_noise(rng, (n_file,), "pink", fs)
            inside = np.flatnonzero((arrival[:, m] * fs < t0 + n_file) & ((arrival[:, m] + 0.5) * fs > t0))
            for e in inside:
                start = int(np.floor(arrival[e, m] * fs))
                shaped = delay_and_scale(calls[e], np.array([arrival[e, m] - start / fs]), gain[e, m : m + 1], fs, calls[e].size + 2)[0]
                a, b = max(start, t0), min(start + shaped.size, t0 + n_file)
                if b > a:  # a call ending just before the file starts adds nothing to it
                    audio[a - t0 : b - t0] += shaped[a - start : b - start]
            sf.write(folder / names[k], np.clip(audio, -1, 1).astype(np.float32), int(fs), subtype="PCM_16")
    raven = directory / "raven"
    raven.mkdir(parents=True, exist_ok=True)
    for m in range(len(mics)):
        begin = arrival[:, m] - 0.02
        end = arrival[:, m] + np.array([c.size for c in calls]) / fs + 0.02
        file_index = np.clip((begin // s.file_s).astype(int), 0, n_files - 1)
        table = pd.DataFrame(
            {
                "Selection": np.arange(1, s.n_calls + 1),
                "View": "Spectrogram 1",
                "Channel": 1,
                "Begin Time (s)": begin,
                "End Time (s)": end,
                "Low Freq (Hz)": [b[0] - 300 for b in bands],
                "High Freq (Hz)": [min(b[1] + 300, fs / 2) for b in bands],
                "Begin File": [names[k] for k in file_index],
                "File Offset (s)": begin - file_index * s.file_s,
                "Species": "synthetic_sweep",
            }
        )
        table.to_csv(raven / f"R{m}.Table.1.selections.txt", sep="\t", index=False)
    return pd.DataFrame(
        {
            "call_id": np.arange(s.n_calls),
            "emission_s": emission,
            col.TRUE_X: xy[:, 0],
            col.TRUE_Y: xy[:, 1],
            col.TRUE_Z: z,
            "low_hz": [b[0] for b in bands],
            "high_hz": [b[1] for b in bands],
            "duration_s": [c.size / fs for c in calls],
        }
    )


def write_window_tables(
    settings: SyntheticSeason, truth: pd.DataFrame, directory: Path, window_s: float = 3.0, step_s: float = 3.0
) -> Path:
    """BirdNET-Analyzer tables of the season in ``directory``: fixed windows per file, as a window classifier reports them.

    Every ``step_s`` from each file's start, a ``window_s`` window gets ``Confidence`` 0.9 where a call
    arrives at that recorder overlapping it by at least 0.1 s (else no row), so one song is reported
    in each window it touches and a bird singing every few seconds makes a chain of consecutive
    windows. Layout: ``directory/birdnet/R<k>.BirdNET.results.csv`` with a ``File`` column.

    Returns
    -------
    pathlib.Path
        The folder of the tables.
    """
    s = settings
    mics = np.asarray(s.mics_m, float)
    xyz = truth[[col.TRUE_X, col.TRUE_Y, col.TRUE_Z]].to_numpy(float)
    arrival = truth["emission_s"].to_numpy(float)[:, None] + np.linalg.norm(xyz[:, None, :] - mics[None], axis=-1) / s.speed_of_sound_m_s
    length = truth["duration_s"].to_numpy(float)
    origin = pd.Timestamp(s.origin)
    n_files = int(np.ceil(s.duration_s / s.file_s))
    out = directory / "birdnet"
    out.mkdir(parents=True, exist_ok=True)
    starts = np.arange(0.0, s.file_s - window_s + 1e-9, step_s)
    for m in range(len(mics)):
        rows = []
        for k in range(n_files):
            name = f"{(origin + pd.Timedelta(seconds=k * s.file_s)):%Y%m%d_%H%M%S}.wav"
            begin = k * s.file_s + starts  # season seconds
            overlap = np.minimum(begin[:, None] + window_s, arrival[None, :, m] + length[None]) - np.maximum(
                begin[:, None], arrival[None, :, m]
            )
            for w in np.flatnonzero((overlap >= 0.1).any(axis=1)):
                rows.append((starts[w], starts[w] + window_s, "Synthetica cantans", "synthetic singer", 0.9, name))
        table = pd.DataFrame(rows, columns=["Start (s)", "End (s)", "Scientific name", "Common name", "Confidence", "File"])
        table.to_csv(out / f"R{m}.BirdNET.results.csv", index=False)
    return out
