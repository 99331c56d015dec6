"""Recordings rendered by an independent simulator: pyroomacoustics' image-source method, outdoors.

The method learns from acoustlab's own simulator; its users need to see what a *different*
simulator costs it before they go to the field. This field source renders labelled events with
`pyroomacoustics <https://github.com/LCAV/pyroomacoustics>`_ (MIT): a room so large that only its
floor matters, walls and ceiling fully absorbing (reflection 0), ``max_order=1`` (direct path and
one ground reflection with a frequency-independent energy absorption), pyroomacoustics' own air
absorption and speed of sound from the event's temperature and humidity, fractional-delay
image sources. Calls come from the site's pool of real dry calls (and synthetic ones where the
site's pool has them), background noise from the site's noise regimes (real recordings where it
has them) at an SNR drawn per event.

Where acoustlab's simulator has a locally reacting impedance ground, trunk scattering, its own
absorption tables and field impairments, this one has none of them: the differences are the
point. Sources lie in and around the array: inside the mics' hull grown by ``inside_expansion``
× the array extent, and ``outside_share`` of the positions between that and ``outside_expansion``
× the array extent, at heights across the site's range, so a benchmark sees the sources a field
study has, including those a simulation of the array's interior never showed the model. The
region is the field source's own, independent of the site's simulated region (so a training
simulation can be widened without moving the evaluation's sources); each event says whether it
lies outside the site's simulated region (``outside_simulated_region``).

``protocol=field_eval field=image_source`` trains on acoustlab's simulation and evaluates on
these recordings (every position withheld): the cross-simulator protocol.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.toolkit.calls import CallPool
from acoustlab.toolkit.geometry import distance_to_polygon_m, sample_in_expanded_hull, source_region
from acoustlab.toolkit.physics import speed_of_sound_m_s
from acoustlab.toolkit.playback_signal import SweepPool
from acoustlab.toolkit.scene_sampling import draw_weather, noise_matrix, noise_std_for_snr

log = logging.getLogger(__name__)

_POSITIONS_STREAM, _EVENT_STREAM, _ARRAY_STREAM = 20, 21, 22
#: What a field's events may emit (``signal``).
SIGNALS = ("calls", "sweep")
#: Metres of fully absorbing room around every mic and source (walls never reflect; this keeps them away).
_ROOM_MARGIN_M = 5.0


class ImageSourceField:
    """Labelled events rendered with pyroomacoustics (a ``acoustlab.core.contracts.FieldSource``).

    Parameters
    ----------
    sample_rate_hz, duration_s : float
        Rate (Hz) and length (s) of every recording (the training simulator's, so features agree).
    n_positions : int
        Source positions (the exchangeable unit of the evaluation).
    events_per_position : int
        Calls rendered at each position (each with its own call, weather, noise and SNR).
    inside_expansion : float
        Inner region: the mics' hull grown by this × the largest mic-to-mic distance.
    outside_share : float
        Share of positions between the inner region and …
    outside_expansion : float
        … the mics' hull grown by this × the largest mic-to-mic distance.
    ground_energy_absorption : float
        Energy absorption coefficient of the ground (0 rigid … 1 no reflection), all frequencies.
    snr_db : sequence of float
        SNR range at the nearest mic, dB.
    onset_s : sequence of float
        Range of the call's emission time within the recording, s.
    include_share_alike : bool
        Also draw CC BY-SA calls.
    temperature_error_c : float
        The events table's temperature (and the speed of sound computed from it) is off by this
        from the air the sound travelled through: a thermometer error (°C).
    mic_position_error_m : float
        The site's mic positions are as stated (GPS); the recorders stand off them by a normal
        error of this standard deviation per horizontal axis, m (``true_array``).
    clock_offset_max_s : float
        Each recorder's clock is off by a constant drawn uniformly in ± this, s (``true_array``).
    array_seed : int, optional
        Seed of those array errors (None: ``seed``); one array, many sets of sources (playbacks and calls).
    seed : int
        Seed of positions and renders (independent of the training simulation's).
    positions_m : list of [x, y] or [x, y, z], optional
        The positions themselves, m (e.g. a playback plan's spots): they replace ``n_positions``
        drawn ones; heights are drawn from the site's range where not given.
    signal : str
        What every event emits: ``calls`` (drawn from the site's species and synthetic calls) or
        ``sweep`` (the playback sweep ``calibrate`` asks for: ``acoustlab.toolkit.playback_signal``).
    """

    #: The events' ``source`` column: which renderer made them.
    source_label = "pyroomacoustics_image_source"

    def __init__(
        self,
        sample_rate_hz: float = 24000.0,
        duration_s: float = 1.1,
        n_positions: int = 60,
        events_per_position: int = 5,
        inside_expansion: float = 0.2,
        outside_share: float = 0.3,
        outside_expansion: float = 0.6,
        ground_energy_absorption: float = 0.4,
        snr_db: Sequence[float] = (5.0, 30.0),
        onset_s: Sequence[float] = (0.05, 0.25),
        include_share_alike: bool = False,
        temperature_error_c: float = 0.0,
        mic_position_error_m: float = 0.0,
        clock_offset_max_s: float = 0.0,
        array_seed: int | None = None,
        seed: int = 2000,
        positions_m: Sequence[Sequence[float]] | None = None,
        signal: str = "calls",
    ) -> None:
        if signal not in SIGNALS:
            raise ConfigError(f"field.signal must be one of {list(SIGNALS)}; got {signal!r}")
        self.signal = signal
        given = None if positions_m is None else np.asarray(positions_m, dtype=float)
        if given is not None:
            if given.ndim != 2 or given.shape[1] not in (2, 3) or len(given) < 2 or not np.isfinite(given).all():
                raise ConfigError(f"field.positions_m must be a list of 2 or more [x, y] or [x, y, z] positions in m; got {positions_m}")
            n_positions = len(given)
        self.positions_m = given
        if n_positions < 2 or events_per_position < 1:
            raise ConfigError(
                f"field.n_positions must be >= 2 and field.events_per_position >= 1; got {n_positions}, {events_per_position}"
            )
        if not 0 <= outside_share <= 1:
            raise ConfigError(f"field.outside_share must lie in [0, 1]; got {outside_share}")
        if not 0 <= ground_energy_absorption <= 1:
            raise ConfigError(f"field.ground_energy_absorption must lie in [0, 1]; got {ground_energy_absorption}")
        if len(snr_db) != 2 or snr_db[0] > snr_db[1] or len(onset_s) != 2 or not 0 <= onset_s[0] <= onset_s[1] < duration_s:
            raise ConfigError(
                f"field.snr_db and field.onset_s must be [low, high] ranges (onset within duration_s); got {snr_db}, {onset_s}"
            )
        self.sample_rate_hz = float(sample_rate_hz)
        self.duration_s = float(duration_s)
        self.n_positions = int(n_positions)
        self.events_per_position = int(events_per_position)
        if outside_share > 0 and not outside_expansion > inside_expansion >= 0:
            raise ConfigError(f"field.outside_expansion ({outside_expansion}) must exceed field.inside_expansion ({inside_expansion}) >= 0")
        self.inside_expansion = float(inside_expansion)
        self.outside_share = float(outside_share)
        self.outside_expansion = float(outside_expansion)
        self.ground_energy_absorption = float(ground_energy_absorption)
        self.snr_db = (float(snr_db[0]), float(snr_db[1]))
        self.onset_s = (float(onset_s[0]), float(onset_s[1]))
        self.include_share_alike = bool(include_share_alike)
        self.temperature_error_c = float(temperature_error_c)
        if not (mic_position_error_m >= 0 and clock_offset_max_s >= 0):
            raise ConfigError(
                f"field.mic_position_error_m and field.clock_offset_max_s must be >= 0; got {mic_position_error_m}, {clock_offset_max_s}"
            )
        self.mic_position_error_m = float(mic_position_error_m)
        self.clock_offset_max_s = float(clock_offset_max_s)
        self.seed = int(seed)
        self.array_seed = self.seed if array_seed is None else int(array_seed)

    def true_array(self, site: Site) -> tuple[np.ndarray, np.ndarray]:
        """Where the recorders really stand, (M, 3) m, and their clock offsets, (M,) s (the site states the mics without error)."""
        rng = np.random.default_rng([self.array_seed, _ARRAY_STREAM])
        mics = site.mic_positions_m.astype(float).copy()
        mics[:, :2] += rng.normal(0.0, self.mic_position_error_m, (site.n_mics, 2)) if self.mic_position_error_m > 0 else 0.0
        clocks = (
            rng.uniform(-self.clock_offset_max_s, self.clock_offset_max_s, site.n_mics)
            if self.clock_offset_max_s > 0
            else np.zeros(site.n_mics)
        )
        return mics, clocks

    def validate(self, site: Site) -> None:
        """Check that pyroomacoustics is installed."""
        try:
            import pyroomacoustics  # noqa: F401
        except ImportError:
            raise ConfigError(
                'field=image_source renders with pyroomacoustics, which is not installed: pip install -e ".[crosssim]"'
            ) from None

    def source_positions(self, site: Site) -> np.ndarray:
        """(K, 3) source positions in m: inside the inner region, and ``outside_share`` of them around it."""
        rng = np.random.default_rng([self.seed, _POSITIONS_STREAM])
        if self.positions_m is not None:
            if self.positions_m.shape[1] == 3:
                return self.positions_m.copy()
            return np.column_stack([self.positions_m, rng.uniform(*site.source_height_range_m, size=len(self.positions_m))])
        n_out = int(round(self.outside_share * self.n_positions))
        inside = sample_in_expanded_hull(rng, site.mic_positions_m, self.inside_expansion, self.n_positions - n_out)
        polygon, buffer_m = source_region(site.mic_positions_m, self.inside_expansion)
        outside = np.empty((0, 2))
        while len(outside) < n_out:
            candidates = sample_in_expanded_hull(rng, site.mic_positions_m, self.outside_expansion, 4 * n_out)
            outside = np.vstack([outside, candidates[distance_to_polygon_m(candidates, polygon) > buffer_m]])
        xy = np.vstack([inside, outside[:n_out]])
        height = rng.uniform(*site.source_height_range_m, size=len(xy))
        return np.column_stack([xy, height])

    def _render(
        self,
        site: Site,
        mics_m: np.ndarray,
        source_m: np.ndarray,
        signal: np.ndarray,
        onset_s: float,
        temperature_c: float,
        humidity_pct: float,
    ) -> tuple[np.ndarray, float]:
        """(M, S) clean recording at ``mics_m`` of ``signal`` emitted at ``onset_s`` from ``source_m``, and pyroomacoustics' speed of sound."""
        import pyroomacoustics as pra

        points = np.vstack([mics_m, source_m])
        offset = np.array([points[:, 0].min() - _ROOM_MARGIN_M, points[:, 1].min() - _ROOM_MARGIN_M, 0.0])
        size = np.array([np.ptp(points[:, 0]), np.ptp(points[:, 1]), points[:, 2].max()]) + np.array([2, 2, 1]) * _ROOM_MARGIN_M
        walls = pra.Material(1.0)
        materials = {
            "floor": pra.Material(self.ground_energy_absorption),
            "ceiling": walls,
            "east": walls,
            "west": walls,
            "north": walls,
            "south": walls,
        }
        room = pra.ShoeBox(
            size,
            fs=int(self.sample_rate_hz),
            max_order=1,
            materials=materials,
            air_absorption=True,
            temperature=float(temperature_c),
            humidity=float(humidity_pct),
        )
        room.add_source(source_m - offset, signal=signal, delay=float(onset_s))
        room.add_microphone_array((mics_m - offset).T)
        room.simulate()
        n_out = int(round(self.duration_s * self.sample_rate_hz))
        out = np.zeros((len(mics_m), n_out))
        rendered = room.mic_array.signals[:, :n_out]
        out[:, : rendered.shape[1]] = rendered
        return out, float(room.c)

    def load(self, site: Site) -> RecordingBatch:
        """Every event: positions × ``events_per_position``, each with its own call, weather, noise and SNR."""
        self.validate(site)
        pool = (
            SweepPool(self.sample_rate_hz)
            if self.signal == "sweep"
            else CallPool(site.species_pool, self.sample_rate_hz, self.include_share_alike)
        )
        positions = self.source_positions(site)
        polygon, buffer_m = source_region(site.mic_positions_m, site.hull_expansion)
        outside_site = distance_to_polygon_m(positions[:, :2], polygon) > buffer_m
        n_out = int(round(self.duration_s * self.sample_rate_hz))
        true_mics, clocks = self.true_array(site)
        audio = np.empty((len(positions) * self.events_per_position, site.n_mics, n_out), dtype=np.float32)
        rows = []
        for event_id in range(audio.shape[0]):
            pid = event_id // self.events_per_position
            source = positions[pid]
            rng = np.random.default_rng([self.seed, _EVENT_STREAM, event_id])
            weather = draw_weather(rng, site)
            call = pool.draw(rng)
            onset = rng.uniform(*self.onset_s)
            snr_db = rng.uniform(*self.snr_db)
            regime = int(rng.integers(len(site.noise_regimes)))
            clean, simulator_c = self._render(
                site, true_mics, source, call.signal, onset, weather.temperature_c, weather.relative_humidity_pct
            )
            if np.any(clocks != 0):
                clean = _delayed(clean, clocks, self.sample_rate_hz)
            nearest = int(np.argmin(np.sqrt(((true_mics - source) ** 2).sum(-1))))
            noise_std = noise_std_for_snr(clean[nearest], call.signal.size / self.sample_rate_hz, self.sample_rate_hz, snr_db)
            audio[event_id] = clean + noise_std * noise_matrix(rng, site, regime, n_out, self.sample_rate_hz)
            rows.append(
                {
                    col.EVENT_ID: event_id,
                    col.POSITION_ID: pid,
                    col.TRUE_X: source[0],
                    col.TRUE_Y: source[1],
                    col.TRUE_Z: source[2],
                    col.TEMPERATURE: weather.temperature_c + self.temperature_error_c,
                    col.HUMIDITY: weather.relative_humidity_pct,
                    # what a user computes from a thermometer (off by temperature_error_c); the renderer used its own formula
                    # and the true temperature (simulator_speed_of_sound_m_s)
                    col.SPEED_OF_SOUND: float(
                        speed_of_sound_m_s(weather.temperature_c + self.temperature_error_c, weather.relative_humidity_pct)
                    ),
                    "simulator_speed_of_sound_m_s": simulator_c,
                    col.SNR: snr_db,
                    "noise_regime": site.noise_regimes[regime].kind,
                    "call": call.label,
                    "call_licence": call.licence,
                    col.EMISSION_TIME: onset,
                    "outside_simulated_region": bool(outside_site[pid]),
                    col.HARDWARE_FAILURE: False,
                    "source": self.source_label,
                }
            )
        log.info("%s field: %d events at %d positions rendered", self.source_label, len(rows), len(positions))
        return RecordingBatch(audio=audio, sample_rate_hz=self.sample_rate_hz, events=pd.DataFrame(rows))


def _delayed(signals: np.ndarray, delay_s: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    """(M, S) each channel delayed by its ``delay_s`` (fractional, by a linear phase; a recorder's clock offset)."""
    n = signals.shape[1]
    padded = 2 * n
    spectrum = np.fft.rfft(signals, n=padded, axis=1)
    freqs = np.fft.rfftfreq(padded, d=1.0 / sample_rate_hz)
    shifted = np.fft.irfft(spectrum * np.exp(-2j * np.pi * freqs[None, :] * np.asarray(delay_s)[:, None]), n=padded, axis=1)
    return shifted[:, :n]
