"""Recordings rendered by acoustlab's own outdoor simulator, with a field study's errors in the array.

``field=image_source`` asks what a *different* simulator costs; this field source asks what the
array's errors cost when the propagation is the one the method learned from: the same events,
positions and injected errors as ``field=image_source`` (recorders off their stated positions,
clocks off, a thermometer off; ``plugins.fields.image_source.ImageSourceField``), rendered by
``plugins.simulators.outdoor.OutdoorSimulator`` (impedance ground, trunk scattering, occlusion,
ISO 9613-1 air absorption) at the recorders' true positions. ``calibrate`` is measured on both
(``experiments/field_calibration.py --field``). The ground is the site's; the image-source
renderer's ``ground_energy_absorption`` is refused here rather than ignored.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np
from scipy import fft as sfft

from acoustlab.core.errors import ConfigError
from acoustlab.core.types import Site
from acoustlab.toolkit.physics import speed_of_sound_m_s
from plugins.fields.image_source import ImageSourceField
from plugins.simulators.outdoor import OutdoorSimulator


class OutdoorField(ImageSourceField):
    """Labelled events rendered by acoustlab's outdoor simulator at the true array (a ``FieldSource``; module docstring).

    Parameters
    ----------
    simulator : mapping, optional
        Keyword arguments of ``OutdoorSimulator`` (the training simulator's, e.g. ``${simulator}``
        without its ``_target_``); its sample rate and duration are this field's. Its own
        impairments stay as given (off by default): the array's errors are this field's.
    **kwargs
        Those of ``ImageSourceField`` (positions, events, SNR, the array's errors, seeds).
    """

    source_label = "acoustlab_outdoor_simulator"

    def __init__(self, simulator: Mapping[str, Any] | None = None, **kwargs: Any) -> None:
        if "ground_energy_absorption" in kwargs:
            raise ConfigError(
                "field.ground_energy_absorption is field=image_source's; field=outdoor renders the site's ground "
                "(simulator.ground): remove it"
            )
        super().__init__(**kwargs)
        options = {k: v for k, v in dict(simulator or {}).items() if k != "_target_"}
        self.simulator = OutdoorSimulator(**{**options, "sample_rate_hz": self.sample_rate_hz, "duration_s": self.duration_s})

    def validate(self, site: Site) -> None:
        """The simulator's checks of the site."""
        self.simulator.validate(site)

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
        """(M, S) clean recording at ``mics_m`` of ``signal`` emitted at ``onset_s`` from ``source_m``, and the speed of sound used.

        The whole recording is one transform (no propagation window), so a source outside the
        site's simulated region is rendered in full.
        """
        n_out = int(round(self.duration_s * self.sample_rate_hz))
        n_fft = sfft.next_fast_len(n_out + signal.size)
        freqs = sfft.rfftfreq(n_fft, d=1.0 / self.sample_rate_hz)
        true_site = dataclasses.replace(site, mic_positions_m=np.asarray(mics_m, dtype=float))
        h = self.simulator.transfer_functions(
            true_site, np.asarray(source_m, dtype=float), temperature_c, humidity_pct, freqs, n_fft, onset_s
        )
        spectrum = sfft.rfft(signal, n=n_fft)
        clean = sfft.irfft(spectrum[None, :] * (h["direct"] + h["ground"] + h["trunks"]), n=n_fft, axis=-1)[:, :n_out]
        return clean, float(speed_of_sound_m_s(temperature_c, humidity_pct))
