"""Speed of the TDOA stage (GCC of every pair → K candidate peaks) per 6-mic event, side by side in one run.

Usage: python benchmarks/bench_tdoa_stage.py [--n-events 64]

On freshly simulated forest events (default simulator, 6 mics, 24 kHz, 1.1 s), the default GCC
settings (β-PHAT, band 300–10,000 Hz, upsample 2, K = 3):

* ``reference``: a textbook batched GCC written here for comparison, as the stage was before:
  cross-spectra of every pair weighted pair by pair, double precision, transforms twice the
  signal length, every lag kept;
* ``acoustlab``: :func:`acoustlab.toolkit.gcc_candidates.pair_candidates` (per-mic weighting,
  transforms only as long as the largest lag needs, single-precision inverse transforms, only
  the lag window kept);
* ``acoustlab, coarse search``: the same with ``search="coarse"`` (``+features.gcc.search=coarse``:
  inverse transforms at the sampling rate, peaks refined on the default's grid;
  :mod:`acoustlab.toolkit.gcc_coarse`);
* ``transforms alone``: only the FFTs either path cannot do without, on the same audio: one
  single-precision forward transform per mic (twice the signal length) and one inverse transform
  per pair (``upsample`` times as long, or as long as the forward one for the coarse search). No
  weighting, no products, no peaks: the floor of each path on this machine.

The reference and the default path pick peaks the same way; the table gives ms per event on one
process and how far their chosen lags differ. Writes benchmarks/results/tdoa_stage.{json,md}.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
import scipy.fft as sfft
from common import compose_cfg, machine, write_results

from acoustlab.core.types import RecordingBatch
from acoustlab.run.registry import build
from acoustlab.stages.sites import site_from_config
from acoustlab.toolkit.dsp import next_fast_len
from acoustlab.toolkit.gcc_candidates import lag_windows_s, pair_candidates

log = logging.getLogger("bench_tdoa_stage")


def reference_candidates(audio: np.ndarray, pairs, fs: float, band, upsample: int, beta: float, windows: np.ndarray, k: int) -> np.ndarray:
    """Top-k lags per pair with the textbook pipeline (see the module docstring), (E, P, k)."""
    n_fft = next_fast_len(2 * audio.shape[-1])
    spectra = sfft.rfft(audio, n=n_fft, axis=-1)
    i_idx, j_idx = np.array(pairs).T
    cross = np.conj(spectra[:, i_idx]) * spectra[:, j_idx]
    cross = cross / np.maximum(np.abs(cross), 1e-30) ** beta
    freqs = sfft.rfftfreq(n_fft, d=1.0 / fs)
    cross = cross * ((freqs >= band[0]) & (freqs <= band[1]))
    n_out = n_fft * upsample
    cc = sfft.fftshift(sfft.irfft(cross, n=n_out, axis=-1), axes=-1)
    lags = (np.arange(n_out) - n_out // 2) / (fs * upsample)
    out = np.full((*cc.shape[:2], k), np.nan)
    for p, max_lag in enumerate(windows):
        window = np.abs(lags) <= max_lag
        seg = cc[:, p, window]
        peak = np.ones_like(seg, dtype=bool)
        peak[:, 1:] &= seg[:, 1:] >= seg[:, :-1]
        peak[:, :-1] &= seg[:, :-1] > seg[:, 1:]
        order = np.argsort(-np.where(peak, seg, -np.inf), axis=-1)[:, :k]
        out[:, p] = lags[window][order]
    return out


def transforms_alone(audio: np.ndarray, n_pairs: int, upsample: int) -> float:
    """Seconds for the forward transform of every mic and one inverse transform per pair (single precision, the GCC's lengths)."""
    n_fft = next_fast_len(2 * audio.shape[-1])
    n_out = n_fft * upsample
    audio = audio.astype(np.float32, copy=False)
    cross = np.zeros((audio.shape[0], n_out // 2 + 1), dtype=np.complex64)  # padded once, as the GCC's own buffer
    start = time.perf_counter()
    spectra = sfft.rfft(audio, n=n_fft, axis=-1)
    seconds = time.perf_counter() - start
    cross[:, :spectra.shape[-1]] = spectra[:, 0]
    start = time.perf_counter()
    for _ in range(n_pairs):
        sfft.irfft(cross, n=n_out, axis=-1)
    return seconds + time.perf_counter() - start


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-events", type=int, default=64)
    opts = parser.parse_args()
    cfg = compose_cfg(["+site=forest"])
    site = site_from_config(cfg.site)
    simulator = build(cfg.simulator, "simulator")
    ids = np.arange(opts.n_events)
    batch = simulator.simulate(site, ids, ids // 5, 0)
    gcc_cfg = cfg.features.gcc
    band, up, beta, k = tuple(gcc_cfg.band_hz), int(gcc_cfg.upsample), float(gcc_cfg.beta), int(gcc_cfg.n_candidates)
    windows = lag_windows_s(site, 0.002)
    start = time.perf_counter()
    reference = reference_candidates(batch.audio, site.mic_pairs, batch.sample_rate_hz, band, up, beta, windows, k)
    t_ref = (time.perf_counter() - start) / opts.n_events
    fresh = RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events)  # no cached candidates
    start = time.perf_counter()
    ours = pair_candidates(fresh, site, k, 0.002, band, str(gcc_cfg.weighting), up, beta)
    t_ours = (time.perf_counter() - start) / opts.n_events
    fresh = RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events)
    start = time.perf_counter()
    coarse = pair_candidates(fresh, site, k, 0.002, band, str(gcc_cfg.weighting), up, beta, search="coarse")
    t_coarse = (time.perf_counter() - start) / opts.n_events
    n_pairs = len(site.mic_pairs)
    t_floor = {"default": transforms_alone(batch.audio, n_pairs, up) / opts.n_events, "coarse": transforms_alone(batch.audio, n_pairs, 1) / opts.n_events}
    top_diff = np.abs(ours.lags_s[..., 0] - reference[..., 0])
    same_top = float(np.mean(top_diff < 1.0 / (batch.sample_rate_hz * up)))
    same_top_coarse = float(np.mean(np.abs(coarse.lags_s[..., 0] - reference[..., 0]) < 1.0 / (batch.sample_rate_hz * up)))
    result = {"machine": machine(), "n_events": opts.n_events, "n_mics": site.n_mics, "sample_rate_hz": batch.sample_rate_hz,
              "samples_per_channel": int(batch.audio.shape[-1]),
              "ms_per_event": {"reference": 1e3 * t_ref, "acoustlab": 1e3 * t_ours, "acoustlab_coarse": 1e3 * t_coarse,
                               "transforms_alone_default": 1e3 * t_floor["default"], "transforms_alone_coarse": 1e3 * t_floor["coarse"]},
              "speedup": t_ref / t_ours, "speedup_coarse": t_ref / t_coarse,
              "share_same_top_peak": same_top, "share_same_top_peak_coarse": same_top_coarse}
    lines = ["# TDOA stage speed (GCC of all 15 pairs → 3 candidate peaks per pair), forest, 6 mics", "",
             f"`python benchmarks/bench_tdoa_stage.py --n-events {opts.n_events}`: {opts.n_events} simulated events, "
             f"{batch.audio.shape[-1]} samples per channel at {batch.sample_rate_hz:.0f} Hz; one process.", "",
             "| implementation | ms per event | speed-up | its transforms alone (ms per event) |", "|---|---|---|---|",
             f"| reference (pair-wise weighting, double precision, full-length transforms) | {1e3 * t_ref:.1f} | 1.0× | |",
             f"| acoustlab `pair_candidates` | {1e3 * t_ours:.2f} | {t_ref / t_ours:.1f}× | {1e3 * t_floor['default']:.2f} |",
             f"| acoustlab, coarse search (`+features.gcc.search=coarse`) | {1e3 * t_coarse:.2f} | {t_ref / t_coarse:.1f}× | "
             f"{1e3 * t_floor['coarse']:.2f} |", "",
             f"Same highest peak (within one lag step) on {100 * same_top:.1f} % of the pairs ({100 * same_top_coarse:.1f} % with the coarse "
             "search). Transforms alone: one single-precision forward transform per mic and one inverse transform per pair at the "
             "path's lengths, nothing else (the floor of each path on this machine)."]
    write_results("tdoa_stage", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
