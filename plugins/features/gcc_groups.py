"""GCC-based feature groups: ``tdoa`` (candidate lags), ``xcorr`` (confidences), ``uncertainty``."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import ConfigError
from acoustlab.core.types import RecordingBatch, Site
from acoustlab.toolkit.dsp import event_band_hz
from acoustlab.toolkit.gcc_candidates import pair_candidates
from acoustlab.toolkit.gcc_coarse import check_search
from acoustlab.toolkit.gcc_torch import check_device, check_memory_gb


class _GccGroup:
    """Shared GCC settings of the ``tdoa``, ``xcorr`` and ``uncertainty`` groups.

    The settings come as one mapping ``gcc`` (``features.gcc`` in the config, so the three groups
    cannot drift apart) and/or as keyword arguments, which take precedence. The GCC itself is
    computed once per batch and kept in the batch's cache (``RecordingBatch.derived``).

    Parameters
    ----------
    gcc : mapping, optional
        Any of the keyword arguments below.
    n_candidates : int
        GCC peaks kept per mic pair.
    max_lag_margin_s : float
        Lag window margin, s, beyond mic distance over the fastest sound speed.
    weighting : {"phat", "beta_phat", "none"}
        Cross-spectrum weighting (see ``acoustlab.toolkit.dsp.gcc``).
    beta : float
        β-PHAT exponent in [0, 1] (used with ``weighting="beta_phat"``).
    upsample : int
        Correlation upsampling before parabolic peak refinement.
    band_hz : (float, float), optional
        Band the cross-spectrum is limited to, Hz.
    device : {"cpu", "cuda", "cuda:N"}
        Where the GCC runs: the numpy/SciPy path, or torch on a GPU (the same peaks up to
        single-precision rounding; ``+features.gcc.device=cuda``, see docs/season.md). Not in the
        default config, so the default cache keys do not name it; set, it is part of the key.
    device_memory_gb : float
        With a GPU device: GPU memory, GiB, one pass of events may take (a feature chunk larger
        than that runs in several passes; ``+features.gcc.device_memory_gb=2`` for a small GPU).
    search : {"fine", "coarse"}
        ``fine``: the peaks of the 1/(2 fs) lag grid (default). ``coarse``: searched on the 1/fs
        grid and refined on the 1/(2 fs) grid by band-limited interpolation, cheaper on the
        CPU with nearly the same first-stage fixes (``acoustlab.toolkit.gcc_coarse``); for the CPU
        path with ``upsample: 2``. Not in the default config; set, it is part of the key.
    min_peak : float, optional
        Field recordings only: a mic whose strongest GCC peak with every other mic is below this
        height (dimensionless, 1 = a perfect match) is left out of that event's solve and flagged
        ``weak_gcc``; None (default) keeps every mic. Read by the solver stage, not by the GCC.
    min_peak_relative : float, optional
        Field recordings only: the same, with the height a share (0–1) of the event's strongest
        pair peak, a scale that holds across recorders and file codings; None (default) off.
    """

    cache_version = "1"
    DEFAULTS = {
        "n_candidates": 3,
        "max_lag_margin_s": 0.002,
        "weighting": "beta_phat",
        "beta": 0.8,
        "upsample": 2,
        "band_hz": (300.0, 10000.0),
        "device": "cpu",
        "device_memory_gb": 4.0,
        "search": "fine",
        "min_peak": None,
        "min_peak_relative": None,
    }

    def __init__(self, gcc: Mapping[str, Any] | None = None, **settings: Any) -> None:
        unknown = sorted((set(gcc or {}) | set(settings)) - set(self.DEFAULTS))
        if unknown:
            raise ConfigError(f"features: unknown GCC settings {unknown}; expected some of {sorted(self.DEFAULTS)}")
        params = {**self.DEFAULTS, **(gcc or {}), **settings}
        n_candidates, weighting, band_hz = params["n_candidates"], params["weighting"], params["band_hz"]
        if n_candidates < 1:
            raise ConfigError(f"features: n_candidates must be >= 1; got {n_candidates}")
        if weighting not in ("phat", "beta_phat", "none"):
            raise ConfigError(f"features.gcc.weighting must be 'phat', 'beta_phat' or 'none'; got {weighting!r}")
        if not 0.0 <= float(params["beta"]) <= 1.0:
            raise ConfigError(f"features.gcc.beta must lie in [0, 1]; got {params['beta']}")
        self.n_candidates = int(n_candidates)
        self.max_lag_margin_s = float(params["max_lag_margin_s"])
        self.weighting = weighting
        self.beta = float(params["beta"])
        self.upsample = int(params["upsample"])
        # PHAT whitens every bin it is given: bins without signal (e.g. above the 11 kHz content
        # of recordings made at 22 kHz) then produce spurious peaks, so restrict it to the calls' band.
        self.band_hz = None if band_hz is None else (float(band_hz[0]), float(band_hz[1]))
        self.device = check_device(params["device"])
        self.device_memory_gb = check_memory_gb(params["device_memory_gb"])
        self.search = check_search(str(params["search"]), self.upsample, device=self.device)
        # read by the field's solver stage (a mic without a peak this high is left out of the solve), not by the GCC
        min_peak = params["min_peak"]
        if min_peak is not None and not (isinstance(min_peak, (int, float)) and 0.0 < float(min_peak) <= 1.0):
            raise ConfigError(f"features.gcc.min_peak must be a GCC height in (0, 1] or null (off); got {min_peak!r}")
        relative = params["min_peak_relative"]
        if relative is not None and not (isinstance(relative, (int, float)) and 0.0 < float(relative) < 1.0):
            raise ConfigError(
                f"features.gcc.min_peak_relative must be a share in (0, 1) of the event's strongest peak or null (off); got {relative!r}"
            )

    def _candidates(self, batch: RecordingBatch, site: Site, band_hz=None):
        band = event_band_hz(batch.events, self.band_hz, batch.sample_rate_hz) if band_hz is None else band_hz
        return pair_candidates(
            batch,
            site,
            self.n_candidates,
            self.max_lag_margin_s,
            band,
            self.weighting,
            self.upsample,
            self.beta,
            device=self.device,
            device_memory_gb=self.device_memory_gb,
            search=self.search,
        )


class TdoaCandidates(_GccGroup):
    """``tdoa``: the K best GCC peak lags of every pair (t_j − t_i, s); the first is the dominant peak."""

    group = "tdoa"

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        rows = []
        for i, j in site.mic_pairs:
            for k in range(self.n_candidates):
                rows.append((col.tdoa_lag(i, j, k + 1), "s", f"lag t_{j} − t_{i} of GCC peak rank {k + 1} within the pair's lag window"))
        return rows

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        cand = self._candidates(batch, site)
        names = [r[0] for r in self.catalog(site)]
        return pd.DataFrame(cand.lags_s.reshape(batch.n_events, -1), columns=names)


class XcorrConfidence(_GccGroup):
    """``xcorr``: GCC heights of the K candidates per pair, plus the dominant height in extra bands."""

    group = "xcorr"

    cache_version = "2"  # 2: extra bands sampled at their own rate (band_limited)

    def __init__(
        self,
        gcc: Mapping[str, Any] | None = None,
        extra_bands_hz: Sequence[Sequence[float]] = ((1000.0, 4000.0),),
        extra_bands_band_limited: bool = True,
        **settings: Any,
    ) -> None:
        super().__init__(gcc, **settings)
        self.extra_bands_hz = [(float(lo), float(hi)) for lo, hi in extra_bands_hz]
        self.extra_bands_band_limited = bool(extra_bands_band_limited)

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        rows = []
        for i, j in site.mic_pairs:
            for k in range(self.n_candidates):
                rows.append((col.xcorr_peak(i, j, k + 1), "1", f"GCC height of peak rank {k + 1}"))
            for lo, hi in self.extra_bands_hz:
                rows.append(
                    (
                        f"xcorr__peak_{i}_{j}_{lo:.0f}_{hi:.0f}hz",
                        "1",
                        f"dominant GCC height with the cross-spectrum limited to {lo:.0f}–{hi:.0f} Hz",
                    )
                )
        return rows

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        cand = self._candidates(batch, site)
        cols = {}
        banded = [
            pair_candidates(
                batch,
                site,
                1,
                self.max_lag_margin_s,
                b,
                self.weighting,
                self.upsample,
                self.beta,
                self.extra_bands_band_limited,
                device=self.device,
                device_memory_gb=self.device_memory_gb,
            )
            for b in self.extra_bands_hz
        ]
        for p, (i, j) in enumerate(site.mic_pairs):
            for k in range(self.n_candidates):
                cols[col.xcorr_peak(i, j, k + 1)] = cand.heights[:, p, k]
            for (lo, hi), b in zip(self.extra_bands_hz, banded, strict=True):
                cols[f"xcorr__peak_{i}_{j}_{lo:.0f}_{hi:.0f}hz"] = b.heights[:, p, 0]
        return pd.DataFrame(cols)


class PeakUncertainty(_GccGroup):
    """``uncertainty``: how clearly the dominant GCC peak stands out, per pair."""

    group = "uncertainty"

    def catalog(self, site: Site) -> list[tuple[str, str, str]]:
        rows = []
        for i, j in site.mic_pairs:
            rows += [
                (f"uncertainty__separability_{i}_{j}", "1", "(h1 − h2) / h1 of the two highest peaks"),
                (f"uncertainty__lag_gap_{i}_{j}_s", "s", "|lag1 − lag2| of the two highest peaks"),
                (f"uncertainty__psr_{i}_{j}_db", "dB", "20 log10(h1 / RMS of the correlation in the lag window)"),
            ]
        return rows

    def transform(self, batch: RecordingBatch, site: Site) -> pd.DataFrame:
        cand = self._candidates(batch, site)
        h1, lag1 = cand.heights[..., 0], cand.lags_s[..., 0]
        h2 = cand.heights[..., 1] if self.n_candidates > 1 else np.zeros_like(h1)
        lag2 = cand.lags_s[..., 1] if self.n_candidates > 1 else lag1
        cols = {}
        with np.errstate(divide="ignore", invalid="ignore"):
            for p, (i, j) in enumerate(site.mic_pairs):
                cols[f"uncertainty__separability_{i}_{j}"] = np.where(h1[:, p] > 0, (h1[:, p] - np.nan_to_num(h2[:, p])) / h1[:, p], 0.0)
                cols[f"uncertainty__lag_gap_{i}_{j}_s"] = np.abs(lag1[:, p] - lag2[:, p])
                cols[f"uncertainty__psr_{i}_{j}_db"] = 20 * np.log10(np.maximum(h1[:, p], 1e-12) / np.maximum(cand.sidelobe[:, p], 1e-12))
        return pd.DataFrame(cols)
