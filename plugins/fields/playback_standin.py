"""A SYNTHETIC stand-in for a real field playback campaign (no real field data is involved).

It imitates what a playback experiment delivers so that the field-evaluation and
leave-one-position-out protocols can run end to end before real recordings exist: K fixed
loudspeaker positions (one with a hardware failure), several playback settings, a fixed stimulus
set per position, field impairments switched on, and propagation deliberately mismatched from the
training simulations (its own weather draws, perturbed ground flow resistivity and air
absorption). Results on it measure robustness to a simulated sim-to-field gap, not field
performance.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.toolkit.calls import Call, CallPool, catalog, synthetic_call
from acoustlab.toolkit.event_physics import assumed_source_height_m
from acoustlab.toolkit.geometry import sample_in_expanded_hull
from plugins.simulators.outdoor import OutdoorSimulator

_POSITIONS_STREAM = 10
_STIMULI_STREAM = 11
_EVENT_STREAM = 12


def build_stimuli(rng: np.random.Generator, sample_rate_hz: float, region: str, count: int, include_share_alike: bool) -> list[Call]:
    """``count`` stimuli for a region: real calls of that region's catalog species, topped up with synthetic calls.

    Real calls are spread over species (round robin); synthetic calls fill the remainder and make up
    at least a quarter of the set.
    """
    table = catalog()
    table = table[(table["region"] == region) & (table["species"] != "ruffed_grouse")]
    if not include_share_alike:
        table = table[table["pool"] == "permissive"]
    by_species = []
    for species in sorted(table["species"].unique()):
        pool = CallPool([species], sample_rate_hz, include_share_alike, synthetic_fraction=0.0)
        calls = list(pool.real)
        rng.shuffle(calls)
        by_species.append(calls)
    n_real = min(count - count // 4, sum(len(c) for c in by_species))
    chosen: list[Call] = []
    while len(chosen) < n_real:
        for calls in by_species:
            if calls and len(chosen) < n_real:
                chosen.append(calls.pop())
    while len(chosen) < count:
        label, signal = synthetic_call(rng, sample_rate_hz)
        chosen.append(Call(label, signal, "generated"))
    return chosen


class PlaybackStandIn:
    """Field-playback stand-in (a ``acoustlab.core.contracts.FieldSource``).

    Parameters
    ----------
    simulator : mapping
        Keyword arguments of ``plugins.simulators.outdoor.OutdoorSimulator`` for the field
        renders (impairments on, perturbations set).
    n_positions : int
        Number of fixed loudspeaker positions K.
    failed_position : int or None
        Index of the position whose recordings suffer a hardware failure (None for none).
    failure : mapping
        ``mic`` (index) and ``mode`` (``dead``, ``clipping`` or ``dc``) of that failure.
    settings_snr_offset_db : sequence of float
        One playback setting per value: SNR offsets in dB (e.g. loud and quiet playback).
    stimuli : mapping
        Number of stimuli per region, e.g. ``{europe: 16, north_america: 30}``.
    include_share_alike : bool
        Allow CC BY-SA stimuli.
    seed : int
        Seed of positions, stimuli and renders (independent of the training simulation's draws).
    """

    def __init__(
        self,
        simulator: Mapping[str, Any],
        n_positions: int = 6,
        failed_position: int | None = 5,
        failure: Mapping[str, Any] | None = None,
        settings_snr_offset_db: Sequence[float] = (0.0, -10.0),
        stimuli: Mapping[str, int] | None = None,
        include_share_alike: bool = False,
        seed: int = 1000,
    ) -> None:
        if n_positions < 2:
            raise ConfigError(f"field.n_positions must be >= 2; got {n_positions}")
        if failed_position is not None and not 0 <= failed_position < n_positions:
            raise ConfigError(f"field.failed_position must be in [0, {n_positions}); got {failed_position}")
        self.simulator = OutdoorSimulator(**dict(simulator))
        self.n_positions = int(n_positions)
        self.failed_position = failed_position
        failure = dict(failure or {"mic": 0, "mode": "clipping"})
        self.failure = (int(failure.get("mic", 0)), str(failure.get("mode", "clipping")))
        self.settings = [float(v) for v in settings_snr_offset_db]
        self.stimuli = dict(stimuli or {"europe": 16, "north_america": 30})
        self.include_share_alike = bool(include_share_alike)
        self.seed = int(seed)

    def speaker_positions(self, site: Site) -> np.ndarray:
        """(K, 3) loudspeaker positions in m, inside the mics' expanded hull, at the site's mid source height."""
        rng = np.random.default_rng([self.seed, _POSITIONS_STREAM])
        xy = sample_in_expanded_hull(rng, site.mic_positions_m, site.hull_expansion, self.n_positions)
        return np.column_stack([xy, np.full(self.n_positions, assumed_source_height_m(site))])

    def load(self, site: Site) -> RecordingBatch:
        """Every playback: positions × settings × stimuli, with impairments and mismatched propagation."""
        if self.failure[0] >= site.n_mics:
            raise ConfigError(f"field.failure.mic={self.failure[0]} but site {site.name!r} has {site.n_mics} mics")
        self.simulator.validate(site)
        sr = self.simulator.sample_rate_hz
        rng = np.random.default_rng([self.seed, _STIMULI_STREAM])
        stimuli = []
        for region, count in self.stimuli.items():
            stimuli += [(region, c) for c in build_stimuli(rng, sr, region, int(count), self.include_share_alike)]
        speakers = self.speaker_positions(site)
        gains = self.simulator.deployment_gains_db(site, self.seed)
        audio, rows = [], []
        event_id = 0
        for pid, speaker in enumerate(speakers):
            failed = pid == self.failed_position
            for setting, offset in enumerate(self.settings):
                for stim_id, (region, call) in enumerate(stimuli):
                    ev_rng = np.random.default_rng([self.seed, _EVENT_STREAM, event_id])
                    rec, row = self.simulator.render_event(
                        site,
                        speaker,
                        ev_rng,
                        call=call,
                        snr_offset_db=offset,
                        forced_failure=self.failure if failed else None,
                        gains_db=gains,
                    )
                    audio.append(rec)
                    rows.append(
                        {
                            col.EVENT_ID: event_id,
                            col.POSITION_ID: pid,
                            col.TRUE_X: speaker[0],
                            col.TRUE_Y: speaker[1],
                            col.TRUE_Z: speaker[2],
                            **row,
                            "setting": setting,
                            "stimulus": stim_id,
                            "stimulus_region": region,
                            col.HARDWARE_FAILURE: failed,
                            "source": "synthetic_playback_standin",
                        }
                    )
                    event_id += 1
        return RecordingBatch(audio=np.stack(audio), sample_rate_hz=sr, events=pd.DataFrame(rows))
