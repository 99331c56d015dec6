"""Outdoor propagation simulator: direct path, ground reflection, trunk scattering, occlusion,
air absorption, real and synthetic calls, real and synthetic noise, optional field impairments.

For every source–mic pair the transfer function is the sum of
- the direct path: 1/R1 spreading, delay R1/c(T, RH), ISO 9613-1 absorption, and trunk
  occlusion (Maekawa diffraction loss and the detour delay of every trunk that blocks the path);
- the ground reflection: image source, Weyl–van der Pol spherical-wave coefficient Q(f) from the
  site's impedance model (Miki or Delany–Bazley, optionally a hard-backed layer), same occlusion;
- single scattering by every trunk: the rigid-cylinder series |A(φ, ka)| (or an isotropic point
  scatterer) with the point-source/infinite-cylinder spreading √(2/(πk)) / √(d1 d2 (d1 + d2)),
  delay (d1 + d2)/c, absorption over d1 + d2; evaluated per frequency band and placed at
  fractional delays, bands recombined by a partition of unity in log frequency. Scattered paths
  within half a wavelength of the direct path (the forward lobe that forms the trunk's shadow) are
  left to the occlusion model, so the shadow is not counted twice.
The dry call is convolved with the summed response in the frequency domain; noise is added at a
sampled SNR at the nearest mic.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from functools import lru_cache
from typing import Any

import numpy as np
import pandas as pd
import scipy.fft as sfft

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.core.types import RecordingBatch, Site, require_range
from acoustlab.toolkit.calls import CallPool
from acoustlab.toolkit.dsp import next_fast_len
from acoustlab.toolkit.geometry import source_region
from acoustlab.toolkit.impairments import (
    FAILURE_MODES,
    INTERFERENCE_KINDS,
    ImpairmentConfig,
    add_interference,
    fail_channel,
)
from acoustlab.toolkit.physics import air_absorption_db_per_m, speed_of_sound_m_s
from acoustlab.toolkit.propagation import (
    cylinder_scattering_magnitude,
    ground_impedance,
    occlusion_attenuation_db,
    segment_trunk_clearance,
    spherical_reflection_coefficient,
    to_fft_convention,
    trunk_detour_m,
)
from acoustlab.toolkit.scene_sampling import (
    draw_source,
    draw_weather,
    event_rng,
    noise_matrix,
    noise_std_for_snr,
)

log = logging.getLogger(__name__)

#: Stream of per-deployment draws (recorder gains), independent of events.
_DEPLOYMENT_STREAM = 2
#: Frequencies at which the ground reflection coefficient is evaluated before interpolation.
_Q_GRID_POINTS = 256
#: Length (samples) of the zero-phase band kernels that shape scattered arrivals.
_BAND_KERNEL_TAPS = 128
#: Relative cost at which per-path kernels beat per-band FFTs for trunk scattering (measured)
_KERNEL_COST_FACTOR = 0.5
#: ISO 9613-2 Annex A octave centres (Hz) for foliage attenuation.
_OCTAVES_HZ = np.array([63, 125, 250, 500, 1000, 2000, 4000, 8000], dtype=float)


def band_weights(freqs_hz: np.ndarray, centres_hz: np.ndarray) -> np.ndarray:
    """(B, F) triangular weights in log frequency that sum to 1 at every frequency."""
    lf = np.log(np.maximum(freqs_hz, 1.0))
    lc = np.log(centres_hz)
    w = np.zeros((centres_hz.size, freqs_hz.size))
    for b in range(centres_hz.size):
        if b > 0:
            rise = (lf - lc[b - 1]) / (lc[b] - lc[b - 1])
            w[b] = np.where((lf >= lc[b - 1]) & (lf <= lc[b]), rise, w[b])
        else:
            w[b] = np.where(lf <= lc[b], 1.0, w[b])
        if b < centres_hz.size - 1:
            fall = (lc[b + 1] - lf) / (lc[b + 1] - lc[b])
            w[b] = np.where((lf > lc[b]) & (lf < lc[b + 1]), fall, w[b])
        else:
            w[b] = np.where(lf > lc[b], 1.0, w[b])
    return w


@lru_cache(maxsize=8)
def band_kernels(sample_rate_hz: float, centres_hz: tuple | np.ndarray, taps: int) -> np.ndarray:
    """(B, taps) zero-phase FIR kernels of the log-frequency bands; they sum to a unit impulse."""
    centres = np.asarray(centres_hz, dtype=float)
    freqs = sfft.rfftfreq(taps, d=1.0 / sample_rate_hz)
    weights = band_weights(np.maximum(freqs, freqs[1] / 2), centres)
    return np.fft.fftshift(sfft.irfft(weights, n=taps, axis=-1), axes=-1)


class OutdoorSimulator:
    """Physics-based outdoor propagation (see the module docstring).

    Parameters
    ----------
    sample_rate_hz : float
        Output sampling rate in Hz.
    duration_s : float
        Recording length in s.
    onset_s : sequence of float
        (low, high) emission time of the call within the recording, in s.
    calls : mapping
        ``include_share_alike`` (bool) and ``synthetic_fraction`` (probability of a synthetic call).
    ground : bool
        Include the ground reflection.
    trunks : mapping
        ``enabled`` (bool), ``model`` (``cylinder`` or ``point``), ``max_range_m`` (ignore trunks
        farther than this from both source and mic; null for all), ``bands_hz`` (band centres).
    occlusion : bool
        Attenuate and delay paths blocked by trunks.
    air_absorption : bool
        Apply ISO 9613-1 absorption on every path.
    foliage_db_per_m : sequence of float, optional
        Foliage attenuation per octave 63 Hz–8 kHz in dB/m (ISO 9613-2 Annex A: 0.02 … 0.12),
        applied over the whole path length; null uses the site's ``foliage_db_per_m``.
    diffuse_noise_fraction : float
        Fraction of the noise power shared by all mics.
    impairments : mapping
        ``acoustlab.toolkit.impairments.ImpairmentConfig`` fields (all off by default).
    perturbation : mapping
        Mismatch knobs for field stand-ins: ``flow_resistivity_factor`` and ``absorption_factor``.
    """

    cache_version = "1"

    def __init__(
        self,
        sample_rate_hz: float = 24000.0,
        duration_s: float = 1.1,
        onset_s: Sequence[float] = (0.02, 0.08),
        calls: Mapping[str, Any] | None = None,
        ground: bool = True,
        trunks: Mapping[str, Any] | None = None,
        occlusion: bool = True,
        air_absorption: bool = True,
        foliage_db_per_m: Sequence[float] | None = None,
        diffuse_noise_fraction: float = 0.0,
        impairments: Mapping[str, Any] | None = None,
        perturbation: Mapping[str, Any] | None = None,
    ) -> None:
        self.sample_rate_hz = float(sample_rate_hz)
        if not self.sample_rate_hz > 0:
            raise ConfigError(f"simulator.sample_rate_hz must be positive; got {sample_rate_hz}")
        if self.sample_rate_hz < 8000:
            raise ConfigError(f"simulator.sample_rate_hz={self.sample_rate_hz} Hz is below twice the 4 kHz band of bird calls; use >= 8000")
        self.duration_s = float(duration_s)
        if not self.duration_s > 0:
            raise ConfigError(f"simulator.duration_s must be positive; got {duration_s}")
        self._onset = require_range("simulator.onset_s", onset_s, lower=0.0)
        calls = dict(calls or {})
        self.include_share_alike = bool(calls.get("include_share_alike", False))
        self.synthetic_fraction = float(calls.get("synthetic_fraction", 0.3))
        self.ground = bool(ground)
        trunks = dict(trunks or {})
        self.trunks_enabled = bool(trunks.get("enabled", True))
        self.trunk_model = str(trunks.get("model", "cylinder"))
        if self.trunk_model not in ("cylinder", "point"):
            raise ConfigError(f"simulator.trunks.model must be 'cylinder' or 'point'; got {self.trunk_model!r}")
        self.trunk_max_range_m = trunks.get("max_range_m")
        self.bands_hz = np.asarray(trunks.get("bands_hz", [250, 500, 1000, 2000, 4000, 8000]), dtype=float)
        self.occlusion = bool(occlusion)
        self.air_absorption = bool(air_absorption)
        self.foliage_db_per_m = None if foliage_db_per_m is None else np.asarray(foliage_db_per_m, dtype=float)
        if self.foliage_db_per_m is not None and self.foliage_db_per_m.size != _OCTAVES_HZ.size:
            raise ConfigError(f"simulator.foliage_db_per_m needs {_OCTAVES_HZ.size} values (63 Hz–8 kHz octaves)")
        self.diffuse_noise_fraction = float(diffuse_noise_fraction)
        if not 0 <= self.diffuse_noise_fraction <= 1:
            raise ConfigError(f"simulator.diffuse_noise_fraction must be in [0, 1]; got {diffuse_noise_fraction}")
        self.impairments = ImpairmentConfig(**dict(impairments or {}))
        perturbation = dict(perturbation or {})
        self.flow_resistivity_factor = float(perturbation.get("flow_resistivity_factor", 1.0))
        self.absorption_factor = float(perturbation.get("absorption_factor", 1.0))
        self._pools: dict[tuple, CallPool] = {}
        self._setup: dict[tuple, tuple] = {}

    # ----------------------------------------------------------------------------------- setup
    def _pool(self, site: Site) -> CallPool:
        key = (site.species_pool, self.sample_rate_hz)
        if key not in self._pools:
            self._pools[key] = CallPool(site.species_pool, self.sample_rate_hz, self.include_share_alike, self.synthetic_fraction)
        return self._pools[key]

    def validate(self, site: Site) -> None:
        """Check the call pool and that the recording fits the farthest source and longest call."""
        pool = self._pool(site)
        polygon, buffer_m = source_region(site.mic_positions_m, site.hull_expansion)
        far = np.sqrt(((polygon[:, None, :] - site.mic_positions_m[None, :, :2]) ** 2).sum(-1)).max() + buffer_m
        c_min = speed_of_sound_m_s(site.temperature_range_c[0], site.relative_humidity_range_pct[0])
        needed = self._onset[1] + far / c_min + pool.max_duration_s
        if needed > self.duration_s:
            raise ConfigError(
                f"simulator.duration_s={self.duration_s} s is too short for site {site.name!r}: the farthest source "
                f"({far:.0f} m) and the longest call ({pool.max_duration_s:.2f} s) need {needed:.2f} s"
            )
        for regime in site.noise_regimes:
            if regime.kind == "band" and regime.band_hz[1] >= self.sample_rate_hz / 2:
                raise ConfigError(f"site noise band {regime.band_hz} Hz reaches the Nyquist frequency of {self.sample_rate_hz} Hz")

    # ------------------------------------------------------------------------------- physics
    def transfer_functions(
        self,
        site: Site,
        source_m: np.ndarray,
        temperature_c: float,
        humidity_pct: float,
        freqs_hz: np.ndarray,
        n_fft: int,
        emission_s: float = 0.0,
        clock_offsets_s: np.ndarray | None = None,
        speed_factors: np.ndarray | None = None,
    ) -> dict[str, np.ndarray]:
        """Per-mic transfer functions (NumPy FFT convention) of each propagation component.

        Parameters
        ----------
        site : Site
            Geometry, trees and ground.
        source_m : numpy.ndarray
            (3,) source position in m.
        temperature_c, humidity_pct : float
            Air state.
        freqs_hz : numpy.ndarray
            (F,) rfft frequencies of an n_fft-point transform, Hz.
        n_fft : int
            Transform length (for the time-domain placement of scattered arrivals).
        emission_s : float
            Emission time of the call, s.
        clock_offsets_s : numpy.ndarray, optional
            (M,) clock errors of the mics, s.
        speed_factors : numpy.ndarray, optional
            (M, 3) relative sound-speed factors of the direct, ground and scattered paths.

        Returns
        -------
        dict of str to numpy.ndarray
            ``direct``, ``ground``, ``trunks``: (M, F) complex; ``delay_direct_s``: (M,).
        """
        mics = site.mic_positions_m
        m = mics.shape[0]
        c = float(speed_of_sound_m_s(temperature_c, humidity_pct))
        clock = np.zeros(m) if clock_offsets_s is None else np.asarray(clock_offsets_s, dtype=float)
        speed = np.ones((m, 3)) if speed_factors is None else np.asarray(speed_factors, dtype=float)
        alpha = np.zeros_like(freqs_hz)
        if self.air_absorption:
            alpha = self.absorption_factor * air_absorption_db_per_m(freqs_hz, temperature_c, humidity_pct)
        foliage = self.foliage_db_per_m if self.foliage_db_per_m is not None else site.foliage_db_per_m
        if foliage is not None:
            alpha = alpha + np.interp(np.log(np.maximum(freqs_hz, 1)), np.log(_OCTAVES_HZ), np.asarray(foliage, dtype=float))
        horiz = np.sqrt(((mics[:, :2] - source_m[:2]) ** 2).sum(-1))
        r1 = np.sqrt(horiz**2 + (mics[:, 2] - source_m[2]) ** 2)

        occ_db = np.zeros((m, freqs_hz.size))
        detour = np.zeros(m)
        trees, radii = site.tree_positions_m, site.trunk_diameters_m / 2
        if self.occlusion and trees.shape[0]:
            dist, frac = segment_trunk_clearance(np.repeat(source_m[None, :2], m, 0), mics[:, :2], trees)
            blocked = (dist < radii[None]) & (frac > 0) & (frac < 1)
            for k, t in zip(*np.nonzero(blocked)):
                along = frac[k, t] * horiz[k]
                d = trunk_detour_m(np.array(along), np.array(horiz[k] - along), radii[t], dist[k, t])
                detour[k] += float(d)
                occ_db[k] += occlusion_attenuation_db(freqs_hz, np.array(d), c)

        def path(length_m: np.ndarray, extra_m: np.ndarray, factor: np.ndarray) -> np.ndarray:
            delay = emission_s + (length_m + extra_m) / (c * factor) + clock
            gain_db = alpha[None, :] * length_m[:, None] + occ_db
            # attenuation and delay in one complex exponential: 10^(−g/20)·e^(−2πifτ) = e^(−g·ln10/20 − 2πifτ)
            exponent = (-np.log(10) / 20) * gain_db - 2j * np.pi * freqs_hz[None, :] * delay[:, None]
            return np.exp(exponent) / length_m[:, None]

        out = {"direct": path(r1, detour, speed[:, 0]), "delay_direct_s": emission_s + (r1 + detour) / (c * speed[:, 0]) + clock}
        if self.ground:
            heights = source_m[2] + mics[:, 2]
            r2 = np.sqrt(horiz**2 + heights**2)
            # Q(f) is smooth in frequency (the delays are in path()), so evaluate it on a coarse
            # log-frequency grid and interpolate: the Faddeeva function is the costly part.
            coarse = np.geomspace(max(freqs_hz[1], 1.0), max(freqs_hz[-1], 2.0), _Q_GRID_POINTS)
            z = ground_impedance(
                coarse,
                site.ground_flow_resistivity_kpa_s_m2 * self.flow_resistivity_factor,
                site.ground_impedance_model,
                site.ground_layer_thickness_m,
                c,
            )
            q_coarse = to_fft_convention(spherical_reflection_coefficient(coarse, z, r2, heights / r2, c))
            lf, lc = np.log(np.maximum(freqs_hz, coarse[0])), np.log(coarse)
            q = np.stack([np.interp(lf, lc, q_coarse[k].real) + 1j * np.interp(lf, lc, q_coarse[k].imag) for k in range(m)])
            out["ground"] = q * path(r2, detour, speed[:, 1])
        else:
            out["ground"] = np.zeros((m, freqs_hz.size), complex)
        out["trunks"] = self._trunk_transfer(
            site, source_m, r1, c, alpha, freqs_hz, n_fft, emission_s, clock, speed[:, 2], temperature_c, humidity_pct
        )
        return out

    def _trunk_transfer(self, site, source_m, r1, c, alpha, freqs_hz, n_fft, emission_s, clock, speed, temperature_c, humidity_pct):
        m = site.n_mics
        trees, radii = site.tree_positions_m, site.trunk_diameters_m / 2
        if not (self.trunks_enabled and trees.shape[0]):
            return np.zeros((m, freqs_hz.size), complex)
        mics = site.mic_positions_m
        d1h = np.sqrt(((trees - source_m[:2]) ** 2).sum(-1))  # (T,)
        d2h = np.sqrt(((trees[None] - mics[:, None, :2]) ** 2).sum(-1))  # (M, T)
        keep = (d1h > radii)[None, :] & (d2h > radii[None, :])
        if self.trunk_max_range_m is not None:
            keep &= (d1h[None, :] <= self.trunk_max_range_m) | (d2h <= self.trunk_max_range_m)
        total = np.sqrt((d1h[None, :] + d2h) ** 2 + (source_m[2] - mics[:, None, 2]) ** 2)
        d1 = total * d1h[None, :] / (d1h[None, :] + d2h)
        d2 = total - d1
        u_in = (trees - source_m[:2]) / np.maximum(d1h, 1e-9)[:, None]  # (T, 2)
        u_out = (mics[:, None, :2] - trees[None]) / np.maximum(d2h, 1e-9)[..., None]  # (M, T, 2)
        angle = np.arccos(np.clip((u_in[None] * u_out).sum(-1), -1, 1))  # 0 = forward
        delay = emission_s + total / (c * speed[:, None]) + clock[:, None]
        in_window = keep & (delay < (n_fft - _BAND_KERNEL_TAPS) / self.sample_rate_hz)
        centres = self.bands_hz[self.bands_hz < self.sample_rate_hz / 2]
        alpha_c = np.interp(centres, freqs_hz, alpha)
        amps = np.zeros((centres.size,) + angle.shape)  # (B, M, T)
        for b, fc in enumerate(centres):
            k = 2 * np.pi * fc / c
            if self.trunk_model == "cylinder":
                mag = cylinder_scattering_magnitude(k * radii[None, :], angle)
            else:
                mag = np.broadcast_to((np.pi / 4) * (k * radii[None, :]) ** 2, angle.shape)
            amp = mag * np.sqrt(2 / (np.pi * k)) / np.sqrt(d1 * d2 * total) * 10 ** (-alpha_c[b] * total / 20)
            forward_lobe = (total - r1[:, None]) < 0.5 * (c / fc)
            amps[b] = np.where(in_window & ~forward_lobe, amp, 0.0)
        active = np.nonzero(amps.any(axis=0))  # (mic, tree) pairs with a scattered arrival
        if not active[0].size:
            return np.zeros((m, freqs_hz.size), complex)
        pos = delay[active] * self.sample_rate_hz
        i0 = np.floor(pos).astype(int)
        frac = pos - i0
        n_paths = active[0].size
        # Two exact ways to shape each arrival by its band amplitudes; take the cheaper one:
        # per-path kernels placed in the time domain (few trees), or one impulse train per band
        # filtered in the frequency domain (many trees).
        if n_paths * _BAND_KERNEL_TAPS <= centres.size * m * n_fft * _KERNEL_COST_FACTOR:
            kernels = band_kernels(self.sample_rate_hz, tuple(centres), _BAND_KERNEL_TAPS)  # (B, L)
            path_kernels = amps[:, active[0], active[1]].T @ kernels  # (P, L)
            half = _BAND_KERNEL_TAPS // 2
            taps = i0[:, None] - half + np.arange(_BAND_KERNEL_TAPS)[None, :]
            flat = active[0][:, None] * n_fft + taps
            ok = (taps >= 0) & (taps < n_fft - 1)
            ir = np.bincount(flat[ok], weights=(path_kernels * (1 - frac)[:, None])[ok], minlength=m * n_fft)
            ir += np.bincount(flat[ok] + 1, weights=(path_kernels * frac[:, None])[ok], minlength=m * n_fft + 1)[: m * n_fft]
            return sfft.rfft(ir.reshape(m, n_fft), axis=-1)
        flat = active[0] * n_fft + i0
        out = np.zeros((m, freqs_hz.size), complex)
        weights = band_weights(freqs_hz, centres)
        for b in range(centres.size):
            a = amps[b][active]
            train = np.bincount(flat, weights=a * (1 - frac), minlength=m * n_fft)
            train += np.bincount(flat + 1, weights=a * frac, minlength=m * n_fft + 1)[: m * n_fft]
            out += weights[b][None, :] * sfft.rfft(train.reshape(m, n_fft), axis=-1)
        return out

    def _audio_setup(self, site: Site) -> tuple[CallPool, int, int, np.ndarray, int]:
        """Call pool, output length, transform length, its frequencies and the propagation window.

        Every arrival (direct, ground, or scattered by any trunk of the site) ends within the
        propagation window, so the response is computed over that window only and the rest of a
        long recording holds noise alone.
        """
        key = (site.name, id(site))
        if key not in self._setup:
            pool = self._pool(site)
            n_out = int(round(self.duration_s * self.sample_rate_hz))
            polygon, buffer_m = source_region(site.mic_positions_m, site.hull_expansion)
            mics = site.mic_positions_m
            heights = max(site.source_height_range_m[1], mics[:, 2].max())
            longest = np.sqrt(((polygon[:, None] - mics[None, :, :2]) ** 2).sum(-1)).max() + buffer_m
            if self.trunks_enabled and site.tree_positions_m.shape[0]:
                trees = site.tree_positions_m
                to_tree = np.sqrt(((polygon[:, None] - trees[None]) ** 2).sum(-1)).max(axis=0) + buffer_m
                from_tree = np.sqrt(((trees[:, None] - mics[None, :, :2]) ** 2).sum(-1)).max(axis=1)
                longest = max(longest, float((to_tree + from_tree).max()))
            c_min = speed_of_sound_m_s(site.temperature_range_c[0], site.relative_humidity_range_pct[0])
            window_s = self._onset[1] + (longest + heights) / (0.98 * c_min) + pool.max_duration_s
            n_prop = min(n_out, int(np.ceil(window_s * self.sample_rate_hz)) + _BAND_KERNEL_TAPS)
            n_fft = next_fast_len(n_prop + int(pool.max_duration_s * self.sample_rate_hz) + _BAND_KERNEL_TAPS)
            self._setup[key] = (pool, n_out, n_fft, sfft.rfftfreq(n_fft, d=1.0 / self.sample_rate_hz), n_prop)
        return self._setup[key]

    def deployment_gains_db(self, site: Site, seed: int) -> np.ndarray:
        """(M,) recorder gain errors in dB, fixed for a deployment (seed)."""
        std = self.impairments.gain_mismatch_db_std
        if not std:
            return np.zeros(site.n_mics)
        return np.random.default_rng([int(seed), _DEPLOYMENT_STREAM]).normal(0, std, site.n_mics)

    def render_event(
        self,
        site: Site,
        source_m: np.ndarray,
        rng: np.random.Generator,
        call: Any = None,
        snr_offset_db: float = 0.0,
        forced_failure: tuple[int, str] | None = None,
        gains_db: np.ndarray | None = None,
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Render one event at ``source_m`` with every random draw taken from ``rng``.

        Parameters
        ----------
        site : Site
            The site.
        source_m : numpy.ndarray
            (3,) source position in m.
        rng : numpy.random.Generator
            The event's generator (weather, SNR, noise, call when ``call`` is None, impairments).
        call : acoustlab.toolkit.calls.Call, optional
            A fixed stimulus; drawn from the site's pool when None.
        snr_offset_db : float
            Added to the drawn SNR (e.g. a quieter playback setting).
        forced_failure : (int, str), optional
            A (mic, mode) hardware failure applied regardless of ``failure_probability``.
        gains_db : numpy.ndarray, optional
            (M,) recorder gain errors in dB.

        Returns
        -------
        audio : numpy.ndarray
            (M, S) float32 recording.
        row : dict
            The event's metadata (weather, SNR, call, impairments), without ids and position.
        """
        pool, n_out, n_fft, freqs, n_prop = self._audio_setup(site)
        m = site.n_mics
        imp = self.impairments
        weather = draw_weather(rng, site)
        snr_db = rng.uniform(*site.snr_range_db) + snr_offset_db
        regime = int(rng.integers(len(site.noise_regimes)))
        call = pool.draw(rng) if call is None else call
        emission = rng.uniform(*self._onset)
        clock = rng.normal(0, imp.clock_offset_std_s, m) if imp.clock_offset_std_s else np.zeros(m)
        speed = 1 + rng.normal(0, imp.sound_speed_perturbation, (m, 3)) if imp.sound_speed_perturbation else np.ones((m, 3))
        h = self.transfer_functions(
            site, source_m, weather.temperature_c, weather.relative_humidity_pct, freqs, n_fft, emission, clock, speed
        )
        spectrum = sfft.rfft(call.signal, n=n_fft)
        clean = np.zeros((m, n_out))
        clean[:, :n_prop] = sfft.irfft(spectrum[None, :] * (h["direct"] + h["ground"] + h["trunks"]), n=n_fft, axis=-1)[:, :n_prop]
        nearest = int(np.argmin(np.sqrt(((site.mic_positions_m - source_m) ** 2).sum(-1))))
        noise_std = noise_std_for_snr(clean[nearest], call.signal.size / self.sample_rate_hz, self.sample_rate_hz, snr_db)
        rec = clean + noise_std * noise_matrix(rng, site, regime, n_out, self.sample_rate_hz, self.diffuse_noise_fraction)
        row: dict[str, Any] = {
            col.TEMPERATURE: weather.temperature_c,
            col.HUMIDITY: weather.relative_humidity_pct,
            col.SPEED_OF_SOUND: float(speed_of_sound_m_s(weather.temperature_c, weather.relative_humidity_pct)),
            col.SNR: snr_db,
            "noise_regime": site.noise_regimes[regime].kind,
            "call": call.label,
            "call_licence": call.licence,
            col.CALL_DURATION: call.signal.size / self.sample_rate_hz,
            col.EMISSION_TIME: emission,
            "interference_mic": -1,
            "interference_kind": "",
            "failed_mic": -1,
            "failure_mode": "",
        }
        if imp.interference_probability and rng.random() < imp.interference_probability:
            mic = int(rng.integers(m))
            kind = INTERFERENCE_KINDS[int(rng.integers(len(INTERFERENCE_KINDS)))]
            rec[mic] = add_interference(rng, rec[mic], self.sample_rate_hz, kind)
            row.update(interference_mic=mic, interference_kind=kind)
        failure = forced_failure
        if failure is None and imp.failure_probability and rng.random() < imp.failure_probability:
            failure = (int(rng.integers(m)), FAILURE_MODES[int(rng.integers(len(FAILURE_MODES)))])
        if failure is not None:
            rec[failure[0]] = fail_channel(rng, rec[failure[0]], failure[1])
            row.update(failed_mic=failure[0], failure_mode=failure[1])
        if gains_db is not None:
            rec = rec * (10 ** (np.asarray(gains_db) / 20))[:, None]
        return rec.astype(np.float32), row

    def simulate(self, site: Site, event_ids: np.ndarray, position_ids: np.ndarray, seed: int) -> RecordingBatch:
        """Render events; see ``acoustlab.core.contracts.Simulator``."""
        event_ids = np.asarray(event_ids, dtype=np.int64)
        position_ids = np.asarray(position_ids, dtype=np.int64)
        _, n_out, _, _, _ = self._audio_setup(site)
        gains_db = self.deployment_gains_db(site, seed)
        audio = np.empty((event_ids.size, site.n_mics, n_out), dtype=np.float32)
        rows = []
        for k, (eid, pid) in enumerate(zip(event_ids, position_ids, strict=True)):
            source = draw_source(site, seed, int(pid))
            audio[k], row = self.render_event(site, source, event_rng(seed, int(eid)), gains_db=gains_db)
            rows.append(
                {
                    col.EVENT_ID: int(eid),
                    col.POSITION_ID: int(pid),
                    col.TRUE_X: source[0],
                    col.TRUE_Y: source[1],
                    col.TRUE_Z: source[2],
                    **row,
                }
            )
        return RecordingBatch(audio=audio, sample_rate_hz=self.sample_rate_hz, events=pd.DataFrame(rows))
