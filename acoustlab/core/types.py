"""Typed data model: sites, batches of recordings and event tables.

Conventions: positions in metres in a local frame (x east, y north, z up); audio as float32
(event × mic × samples); one row per event in every table, keyed by ``event_id``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError, DataError

#: Columns every event table carries (true position NaN where unknown).
EVENT_COLUMNS = (
    col.EVENT_ID,
    col.POSITION_ID,
    col.TRUE_X,
    col.TRUE_Y,
    col.TRUE_Z,
    col.TEMPERATURE,
    col.HUMIDITY,
)


@dataclass(frozen=True)
class NoiseRegime:
    """One kind of background noise a site can have.

    Parameters
    ----------
    kind : str
        ``recorded`` (segments of real recordings), ``white``, ``pink`` or ``band`` (band-limited
        white noise between ``band_hz``).
    files : tuple of str
        Recordings for ``recorded`` (paths or ``acoustlab://`` URIs).
    band_hz : tuple of float or None
        (low, high) in Hz for ``band``.
    """

    kind: str
    files: tuple[str, ...] = ()
    band_hz: tuple[float, float] | None = None


@dataclass(frozen=True)
class Site:
    """A field site: array geometry, trees, weather, ground, noise and species.

    Parameters
    ----------
    name : str
        Site name (used in run names and caches).
    mic_positions_m : numpy.ndarray
        (M, 3) microphone positions in m.
    tree_positions_m : numpy.ndarray
        (T, 2) trunk centre positions in m (empty for open sites).
    trunk_diameters_m : numpy.ndarray
        (T,) trunk diameters at breast height in m.
    temperature_range_c : tuple of float
        (low, high) air temperature in °C.
    relative_humidity_range_pct : tuple of float
        (low, high) relative humidity in %.
    ground_type : str
        Free-text ground description, e.g. ``snow_over_ice``.
    ground_flow_resistivity_kpa_s_m2 : float
        Effective flow resistivity of the ground in kPa·s·m⁻².
    ground_impedance_model : str
        ``miki``, ``delany_bazley`` or ``rigid``.
    ground_layer_thickness_m : float or None
        Thickness of a hard-backed porous layer (snow over ice) in m; None for a deep ground.
    noise_regimes : tuple of NoiseRegime
        Background-noise kinds drawn uniformly per event.
    snr_range_db : tuple of float
        (low, high) signal-to-noise ratio in dB at the nearest microphone.
    species_pool : tuple of str
        Species whose calls the site's simulations draw from.
    source_height_range_m : tuple of float
        (low, high) source height above ground in m.
    hull_expansion : float
        Sources are drawn inside the mics' convex hull grown by this fraction of the largest
        mic-to-mic distance.
    foliage_db_per_m : tuple of float or None
        Foliage attenuation in dB/m for the octaves 63 Hz … 8 kHz (ISO 9613-2 Annex A), applied
        along every path; None for open sites.
    """

    name: str
    mic_positions_m: np.ndarray
    tree_positions_m: np.ndarray
    trunk_diameters_m: np.ndarray
    temperature_range_c: tuple[float, float]
    relative_humidity_range_pct: tuple[float, float]
    ground_type: str
    ground_flow_resistivity_kpa_s_m2: float
    ground_impedance_model: str
    ground_layer_thickness_m: float | None
    noise_regimes: tuple[NoiseRegime, ...]
    snr_range_db: tuple[float, float]
    species_pool: tuple[str, ...]
    source_height_range_m: tuple[float, float]
    hull_expansion: float
    foliage_db_per_m: tuple[float, ...] | None = None

    @property
    def n_mics(self) -> int:
        """Number of microphones."""
        return int(self.mic_positions_m.shape[0])

    @property
    def mic_pairs(self) -> list[tuple[int, int]]:
        """All microphone pairs (i, j) with i < j, in a stable order."""
        return [(i, j) for i in range(self.n_mics) for j in range(i + 1, self.n_mics)]

    @property
    def max_mic_distance_m(self) -> float:
        """Largest mic-to-mic distance (array aperture) in m."""
        d = self.mic_positions_m[:, None, :] - self.mic_positions_m[None, :, :]
        return float(np.sqrt((d**2).sum(-1)).max())

    def fingerprint(self) -> dict[str, Any]:
        """A JSON-able description of everything that defines the site (for cache keys)."""
        return {
            "name": self.name,
            "mic_positions_m": np.round(self.mic_positions_m, 9).tolist(),
            "tree_positions_m": np.round(self.tree_positions_m, 9).tolist(),
            "trunk_diameters_m": np.round(self.trunk_diameters_m, 9).tolist(),
            "temperature_range_c": list(self.temperature_range_c),
            "relative_humidity_range_pct": list(self.relative_humidity_range_pct),
            "ground_type": self.ground_type,
            "ground_flow_resistivity_kpa_s_m2": self.ground_flow_resistivity_kpa_s_m2,
            "ground_impedance_model": self.ground_impedance_model,
            "ground_layer_thickness_m": self.ground_layer_thickness_m,
            "noise_regimes": [{"kind": r.kind, "files": list(r.files), "band_hz": r.band_hz} for r in self.noise_regimes],
            "snr_range_db": list(self.snr_range_db),
            "species_pool": list(self.species_pool),
            "source_height_range_m": list(self.source_height_range_m),
            "hull_expansion": self.hull_expansion,
            "foliage_db_per_m": None if self.foliage_db_per_m is None else list(self.foliage_db_per_m),
        }


@dataclass
class RecordingBatch:
    """A batch of multichannel recordings of acoustic events.

    Parameters
    ----------
    audio : numpy.ndarray
        (E, M, S) float32 pressure signals (arbitrary but common scale).
    sample_rate_hz : float
        Sampling rate in Hz.
    events : pandas.DataFrame
        One row per event with at least ``EVENT_COLUMNS``: ``event_id``, ``position_id`` (the
        exchangeable group), true source position ``x_m, y_m, z_m`` (NaN when unknown),
        ``temperature_c`` and ``relative_humidity_pct``; further columns are metadata.
    """

    audio: np.ndarray
    sample_rate_hz: float
    events: pd.DataFrame = field(default_factory=pd.DataFrame)
    #: Results derived from this batch's audio that several stages share (see ``derived``).
    _derived: dict[Hashable, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.audio.ndim != 3:
            raise DataError(f"RecordingBatch.audio must be (events, mics, samples); got shape {self.audio.shape}")
        if not self.sample_rate_hz > 0:
            raise DataError(f"RecordingBatch.sample_rate_hz must be positive; got {self.sample_rate_hz}")
        missing = [c for c in EVENT_COLUMNS if c not in self.events.columns]
        if missing:
            raise DataError(f"RecordingBatch.events lacks columns {missing}; expected {list(EVENT_COLUMNS)}")
        if len(self.events) != self.audio.shape[0]:
            raise DataError(f"RecordingBatch has {self.audio.shape[0]} audio events but {len(self.events)} event rows")

    @property
    def n_events(self) -> int:
        """Number of events."""
        return int(self.audio.shape[0])

    def derived(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """An explicit per-batch cache: ``compute()`` once per ``key``, then the stored result.

        Feature groups that share an expensive intermediate (e.g. the GCC of every mic pair) key it
        by the settings that determine it; the cache lives and dies with the batch.
        """
        if key not in self._derived:
            self._derived[key] = compute()
        return self._derived[key]

    @property
    def true_position_m(self) -> np.ndarray:
        """(E, 3) true source positions in m (NaN where unknown)."""
        return self.events[[col.TRUE_X, col.TRUE_Y, col.TRUE_Z]].to_numpy(dtype=float)


def stable_hash(obj: Any) -> str:
    """SHA-256 (hex) of the canonical JSON of ``obj`` (sorted keys, numpy-aware)."""

    def default(o: Any) -> Any:
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, (np.integer,)):
            return int(o)
        if isinstance(o, (np.floating,)):
            return float(o)
        if isinstance(o, tuple):
            return list(o)
        raise TypeError(f"cannot hash object of type {type(o).__name__}")

    text = json.dumps(obj, sort_keys=True, default=default, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def require_range(name: str, value: Any, *, lower: float | None = None, upper: float | None = None) -> tuple[float, float]:
    """Validate a (low, high) range from a config, optionally within [lower, upper], and return it as floats."""
    try:
        low, high = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a [low, high] pair of numbers; got {value!r}") from None
    if not (np.isfinite(low) and np.isfinite(high)) or low > high:
        raise ConfigError(f"{name} must be a finite [low, high] pair with low <= high; got {value!r}")
    if lower is not None and low < lower:
        raise ConfigError(f"{name} must not go below {lower}; got {value!r}")
    if upper is not None and high > upper:
        raise ConfigError(f"{name} must not go above {upper:g}; got {value!r}")
    return low, high
