"""Free-field simulator: direct path only, with synthetic chirp calls and noise at a sampled SNR.

The simplest honest propagation model: spherical spreading (1/r) and a fractional delay of r/c
with c from the event's sampled temperature and humidity. No ground, trunks or air absorption.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.core.types import RecordingBatch, Site, require_range
from acoustlab.toolkit.calls import tapered_chirp as synthetic_chirp
from acoustlab.toolkit.dsp import delay_and_scale
from acoustlab.toolkit.geometry import sample_in_expanded_hull, source_region
from acoustlab.toolkit.physics import speed_of_sound_m_s
from acoustlab.toolkit.scene_sampling import noise_matrix

log = logging.getLogger(__name__)

#: Stream tags for per-event random generators (positions and events draw from separate streams).
_POSITION_STREAM = 0
_EVENT_STREAM = 1


#: The synthetic call pool: two linear FM sweeps and a logarithmic whistle (ranges sampled per event).
DEFAULT_CALLS = (
    {"name": "up_sweep", "method": "linear", "f_start_hz": (1500.0, 3000.0), "f_end_hz": (4000.0, 6500.0), "duration_s": (0.08, 0.3)},
    {"name": "down_sweep", "method": "linear", "f_start_hz": (4000.0, 6500.0), "f_end_hz": (1500.0, 3000.0), "duration_s": (0.08, 0.3)},
    {
        "name": "log_whistle",
        "method": "logarithmic",
        "f_start_hz": (2000.0, 3000.0),
        "f_end_hz": (3500.0, 5000.0),
        "duration_s": (0.15, 0.35),
    },
)


class FreeFieldSimulator:
    """Direct-path simulator with synthetic FM-chirp calls.

    Parameters
    ----------
    sample_rate_hz : float
        Output sampling rate in Hz.
    duration_s : float
        Length of each recording in s.
    onset_s : sequence of float
        (low, high) emission time of the call within the recording, in s.
    calls : sequence of mapping
        The call pool. Each entry: ``name``, ``method`` (scipy chirp method), and [low, high]
        ranges ``f_start_hz``, ``f_end_hz``, ``duration_s`` sampled per event (default
        ``DEFAULT_CALLS``, as ``conf/simulator/free_field.yaml``).
    """

    cache_version = "1"

    def __init__(
        self,
        sample_rate_hz: float = 16000.0,
        duration_s: float = 1.0,
        onset_s: Sequence[float] = (0.02, 0.08),
        calls: Sequence[Mapping[str, Any]] = DEFAULT_CALLS,
    ) -> None:
        self.sample_rate_hz = float(sample_rate_hz)
        self.duration_s = float(duration_s)
        self.onset_s = tuple(onset_s)
        self.calls = [dict(c) for c in calls]
        if not self.sample_rate_hz > 0:
            raise ConfigError(f"simulator.sample_rate_hz must be positive; got {sample_rate_hz}")
        if not self.duration_s > 0:
            raise ConfigError(f"simulator.duration_s must be positive; got {duration_s}")
        if not self.calls:
            raise ConfigError("simulator.calls is empty; the call pool needs at least one call")
        self._call_ranges = []
        for i, c in enumerate(self.calls):
            ranges = {k: require_range(f"simulator.calls[{i}].{k}", c.get(k), lower=0.0) for k in ("f_start_hz", "f_end_hz", "duration_s")}
            nyquist = self.sample_rate_hz / 2
            if max(ranges["f_start_hz"][1], ranges["f_end_hz"][1]) >= nyquist:
                raise ConfigError(
                    f"simulator.calls[{i}] reaches {max(ranges['f_start_hz'][1], ranges['f_end_hz'][1])} Hz, "
                    f"at or above the Nyquist frequency {nyquist} Hz of sample_rate_hz={self.sample_rate_hz}"
                )
            self._call_ranges.append((str(c.get("name", f"call{i}")), str(c.get("method", "linear")), ranges))
        self._onset = require_range("simulator.onset_s", self.onset_s, lower=0.0)

    def validate(self, site: Site) -> None:
        """Check the recording is long enough for the farthest source at the slowest sound speed."""
        polygon, buffer_m = source_region(site.mic_positions_m, site.hull_expansion)
        mics_xy = site.mic_positions_m[:, :2]
        far = np.sqrt(((polygon[:, None, :] - mics_xy[None]) ** 2).sum(-1)).max() + buffer_m
        c_min = speed_of_sound_m_s(site.temperature_range_c[0], site.relative_humidity_range_pct[0])
        longest_call = max(r["duration_s"][1] for _, _, r in self._call_ranges)
        needed = self._onset[1] + far / c_min + longest_call
        if needed > self.duration_s:
            raise ConfigError(
                f"simulator.duration_s={self.duration_s} s is too short for site {site.name!r}: the farthest "
                f"source ({far:.0f} m) needs {needed:.2f} s (onset + travel + longest call)"
            )
        for regime in site.noise_regimes:
            if regime.kind == "band" and regime.band_hz[1] >= self.sample_rate_hz / 2:
                raise ConfigError(f"site noise band {regime.band_hz} Hz reaches the Nyquist frequency of {self.sample_rate_hz} Hz")

    def simulate(self, site: Site, event_ids: np.ndarray, position_ids: np.ndarray, seed: int) -> RecordingBatch:
        """Render events; see ``acoustlab.core.contracts.Simulator``."""
        event_ids = np.asarray(event_ids, dtype=np.int64)
        position_ids = np.asarray(position_ids, dtype=np.int64)
        n_samples = int(round(self.duration_s * self.sample_rate_hz))
        mics = site.mic_positions_m
        audio = np.empty((event_ids.size, site.n_mics, n_samples), dtype=np.float32)
        rows = []
        for k, (eid, pid) in enumerate(zip(event_ids, position_ids, strict=True)):
            pos_rng = np.random.default_rng([seed, _POSITION_STREAM, int(pid)])
            xy = sample_in_expanded_hull(pos_rng, mics, site.hull_expansion, 1)[0]
            z = pos_rng.uniform(*site.source_height_range_m)
            source = np.array([xy[0], xy[1], z])
            rng = np.random.default_rng([seed, _EVENT_STREAM, int(eid)])
            temperature_c = rng.uniform(*site.temperature_range_c)
            humidity_pct = rng.uniform(*site.relative_humidity_range_pct)
            snr_db = rng.uniform(*site.snr_range_db)
            regime_index = int(rng.integers(len(site.noise_regimes)))
            call_index = int(rng.integers(len(self._call_ranges)))
            name, method, ranges = self._call_ranges[call_index]
            f0, f1, dur = (rng.uniform(*ranges[key]) for key in ("f_start_hz", "f_end_hz", "duration_s"))
            onset = rng.uniform(*self._onset)
            call = synthetic_chirp(f0, f1, dur, self.sample_rate_hz, method)
            c = speed_of_sound_m_s(temperature_c, humidity_pct)
            dist = np.sqrt(((mics - source) ** 2).sum(-1))
            clean = delay_and_scale(call, onset + dist / c, 1.0 / dist, self.sample_rate_hz, n_samples)
            # SNR is defined at the nearest mic: received call power over the call's duration vs noise power.
            signal_power = np.mean(call**2) / dist.min() ** 2
            noise_std = np.sqrt(signal_power / 10 ** (snr_db / 10))
            audio[k] = clean + noise_std * noise_matrix(rng, site, regime_index, n_samples, self.sample_rate_hz)
            rows.append(
                {
                    col.EVENT_ID: int(eid),
                    col.POSITION_ID: int(pid),
                    col.TRUE_X: source[0],
                    col.TRUE_Y: source[1],
                    col.TRUE_Z: source[2],
                    col.TEMPERATURE: temperature_c,
                    col.HUMIDITY: humidity_pct,
                    col.SPEED_OF_SOUND: c,
                    col.SNR: snr_db,
                    "noise_regime": site.noise_regimes[regime_index].kind,
                    "call": f"synthetic:{name}",
                    "call_f_start_hz": f0,
                    "call_f_end_hz": f1,
                    col.CALL_DURATION: dur,
                    col.EMISSION_TIME: onset,
                }
            )
        return RecordingBatch(audio=audio, sample_rate_hz=self.sample_rate_hz, events=pd.DataFrame(rows))
