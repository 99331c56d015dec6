"""What to play back for ``calibrate``: a linear sweep, whose time differences have one sharp peak.

A calibration measures each mic pair's time difference as the lag of a GCC peak. A bird's song is
tonal or harmonic: its cross-correlation repeats at the song's period, so each pair has several
peaks of almost equal height one period apart, and from few spots a set of such neighbouring
picks fits as tightly as the right one, the calibration trading the thermometer against the
array's scale. A linear sweep passes every frequency of its band once, so its correlation has a
single peak as narrow as the band allows (1/7 ms for 1–8 kHz). What that buys is measured in
``experiments/field_calibration.py`` (docs/calibrate.md, "What to play back"). Swept sines are the
standard measurement signal of room and outdoor acoustics for the same reason.

The sweep is tapered (a Tukey window over 20 % of it) so that a speaker does not click.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import soundfile as sf

from acoustlab.core.errors import ConfigError
from acoustlab.toolkit.calls import Call, tapered_chirp

#: The recommended sweep: 1–8 kHz (most birds' band, and what a field speaker reproduces), 0.3 s.
SWEEP_START_HZ, SWEEP_END_HZ, SWEEP_DURATION_S = 1000.0, 8000.0, 0.3
#: ``Call.label`` of the sweep in rendered events (their ``call`` column).
SWEEP_LABEL = "playback:sweep"


def playback_sweep(
    sample_rate_hz: float,
    f_start_hz: float = SWEEP_START_HZ,
    f_end_hz: float = SWEEP_END_HZ,
    duration_s: float = SWEEP_DURATION_S,
) -> np.ndarray:
    """(S,) a linear sweep from ``f_start_hz`` to ``f_end_hz`` (Hz) over ``duration_s`` (s), unit peak.

    Raises
    ------
    ConfigError
        Where the band is not rising, reaches above 0.45 × ``sample_rate_hz`` or the sweep is shorter than 10 ms.
    """
    rate = float(sample_rate_hz)
    if not 0 < f_start_hz < f_end_hz <= 0.45 * rate:
        raise ConfigError(
            f"playback sweep: need 0 < f_start_hz < f_end_hz <= 0.45 x the sample rate ({0.45 * rate:.0f} Hz); got {f_start_hz}, {f_end_hz}"
        )
    if duration_s < 0.01:
        raise ConfigError(f"playback sweep: duration_s must be >= 0.01 s; got {duration_s}")
    x = tapered_chirp(float(f_start_hz), float(f_end_hz), float(duration_s), rate)
    return x / np.max(np.abs(x))


class SweepPool:
    """A call pool of one call, the playback sweep (what the simulated fields emit with ``signal=sweep``).

    It has ``CallPool``'s interface (``draw``, ``max_duration_s``) and draws nothing from the generator.
    """

    def __init__(self, sample_rate_hz: float) -> None:
        self.sample_rate_hz = float(sample_rate_hz)
        self.call = Call(SWEEP_LABEL, playback_sweep(self.sample_rate_hz), "generated")

    def __len__(self) -> int:
        return 1

    def draw(self, rng: np.random.Generator) -> Call:
        """The sweep (``rng`` is not used)."""
        return self.call

    @property
    def max_duration_s(self) -> float:
        """The sweep's length, s."""
        return self.call.signal.size / self.sample_rate_hz


def write_playback_sweep(
    path: str | Path,
    sample_rate_hz: float = 48000.0,
    f_start_hz: float = SWEEP_START_HZ,
    f_end_hz: float = SWEEP_END_HZ,
    duration_s: float = SWEEP_DURATION_S,
    silence_s: float = 0.5,
) -> Path:
    """Write the sweep to an audio file for a field speaker, with ``silence_s`` (s) of silence before and after.

    The format follows the suffix (``.wav``, ``.flac``; 16-bit PCM); the peak is at −1 dBFS so
    that the file does not clip through a player's resampling.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    path = Path(path)
    pad = np.zeros(int(round(silence_s * sample_rate_hz)))
    signal = 10 ** (-1 / 20) * playback_sweep(sample_rate_hz, f_start_hz, f_end_hz, duration_s)
    try:
        sf.write(path, np.concatenate([pad, signal, pad]), int(round(sample_rate_hz)), subtype="PCM_16")
    except (sf.LibsndfileError, TypeError, ValueError) as error:
        raise ConfigError(f"playback sweep: cannot write {path} ({error}); give a .wav or .flac path in an existing folder") from None
    return path
