"""Speed of the TDOA stage (GCC of every pair → K candidate peaks) per 6-mic event, side by side in one run.

Usage: python benchmarks/bench_tdoa_stage.py [--n-events 160]

On freshly simulated forest events (default simulator, 6 mics, 24 kHz, 1.1 s), the default GCC
settings (β-PHAT, band 300–10,000 Hz, upsample 2, K = 3):

* ``reference``: a textbook batched GCC written here for comparison, as the stage was before:
  cross-spectra of every pair weighted pair by pair, double precision, transforms twice the
  signal length, every lag kept;
* ``acoustlab``: :func:`acoustlab.toolkit.gcc_candidates.pair_candidates` (per-mic weighting,
  cross-spectra multiplied into one zero-padded buffer, single-precision inverse transforms, only
  the lag window kept; transforms twice the signal length like the reference's);
* ``acoustlab, coarse search``: the same with ``search="coarse"`` (``+features.gcc.search=coarse``:
  inverse transforms at the sampling rate, peaks refined on the default's grid;
  :mod:`acoustlab.toolkit.gcc_coarse`);
* ``transforms alone``: only the FFTs either path cannot do without, on the same audio: one
  single-precision forward transform per mic (twice the signal length) and one inverse transform
  per pair (``upsample`` times as long, or as long as the forward one for the coarse search). No
  weighting, no products, no peaks: the floor of each path on this machine.

The reference and the default path pick peaks the same way. Every path runs as ``protocol=season``
runs it: batches of ``protocol.batch_events`` (16) events, with the season loop's malloc settings
(:func:`acoustlab.core.heap.keep_freed_memory`), after one warm-up batch (the coarse search's
compiled kernel loads on its first call), BLAS and OpenMP held to one thread. The table gives ms
per event (wall, and the process's CPU time, so one core is visible) and how far the chosen lags
differ. Writes benchmarks/results/tdoa_stage.{json,md}.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
import scipy.fft as sfft
from common import compose_cfg, machine, write_results
from threadpoolctl import threadpool_limits

from acoustlab.core.heap import keep_freed_memory

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


def transforms_alone(audio: np.ndarray, n_pairs: int, upsample: int) -> None:
    """The forward transform of every mic and one inverse transform per pair (single precision, the GCC's lengths), nothing else."""
    n_fft = next_fast_len(2 * audio.shape[-1])
    n_out = n_fft * upsample
    spectra = sfft.rfft(audio.astype(np.float32, copy=False), n=n_fft, axis=-1)
    cross = np.zeros((audio.shape[0], n_out // 2 + 1), dtype=np.complex64)  # the GCC's zero-padded buffer
    cross[:, :spectra.shape[-1]] = spectra[:, 0]
    for _ in range(n_pairs):
        sfft.irfft(cross, n=n_out, axis=-1)


def per_event(fn, audio: np.ndarray, batch_events: int) -> tuple[float, float, list]:
    """Wall and CPU ms per event of ``fn(audio part)`` over ``audio`` in batches of ``batch_events``, after one warm-up batch, and
    what each batch returned."""
    fn(audio[:batch_events])
    out, wall, cpu = [], time.perf_counter(), time.process_time()
    for first in range(0, audio.shape[0], batch_events):
        out.append(fn(audio[first:first + batch_events]))
    n = audio.shape[0]
    return 1e3 * (time.perf_counter() - wall) / n, 1e3 * (time.process_time() - cpu) / n, out


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-events", type=int, default=160)
    opts = parser.parse_args()
    cfg = compose_cfg(["+site=forest"])
    cfg_season = compose_cfg(["+site=forest", "protocol=season"])  # the season's batch size
    site = site_from_config(cfg.site)
    simulator = build(cfg.simulator, "simulator")
    ids = np.arange(opts.n_events)
    batch = simulator.simulate(site, ids, ids // 5, 0)
    gcc_cfg = cfg.features.gcc
    band, up, beta, k = tuple(gcc_cfg.band_hz), int(gcc_cfg.upsample), float(gcc_cfg.beta), int(gcc_cfg.n_candidates)
    windows = lag_windows_s(site, 0.002)
    batch_events = int(cfg_season.protocol.batch_events)
    events = batch.events.reset_index(drop=True)

    def candidates(search: str):
        def run(audio: np.ndarray):  # a fresh batch each time: nothing cached
            return pair_candidates(RecordingBatch(audio, batch.sample_rate_hz, events.iloc[:audio.shape[0]]), site, k, 0.002, band,
                                   str(gcc_cfg.weighting), up, beta, search=search)
        return run

    n_pairs = len(site.mic_pairs)
    runs = {"reference": lambda a: reference_candidates(a, site.mic_pairs, batch.sample_rate_hz, band, up, beta, windows, k),
            "acoustlab": candidates("fine"), "acoustlab_coarse": candidates("coarse"),
            "transforms_alone_default": lambda a: transforms_alone(a, n_pairs, up),
            "transforms_alone_coarse": lambda a: transforms_alone(a, n_pairs, 1)}
    keep_freed_memory()
    ms, cpu_ms, outputs = {}, {}, {}
    with threadpool_limits(1):
        for name, fn in runs.items():
            ms[name], cpu_ms[name], outputs[name] = per_event(fn, batch.audio, batch_events)
    reference = np.concatenate(outputs["reference"])
    ours = np.concatenate([c.lags_s for c in outputs["acoustlab"]])
    coarse = np.concatenate([c.lags_s for c in outputs["acoustlab_coarse"]])
    t_ref, t_ours, t_coarse = ms["reference"], ms["acoustlab"], ms["acoustlab_coarse"]
    t_floor = {"default": ms["transforms_alone_default"], "coarse": ms["transforms_alone_coarse"]}
    top_diff = np.abs(ours[..., 0] - reference[..., 0])
    same_top = float(np.mean(top_diff < 1.0 / (batch.sample_rate_hz * up)))
    same_top_coarse = float(np.mean(np.abs(coarse[..., 0] - reference[..., 0]) < 1.0 / (batch.sample_rate_hz * up)))
    result = {"machine": machine(), "n_events": opts.n_events, "n_mics": site.n_mics, "sample_rate_hz": batch.sample_rate_hz,
              "samples_per_channel": int(batch.audio.shape[-1]),
              "batch_events": batch_events, "ms_per_event": ms, "cpu_ms_per_event": cpu_ms,
              "speedup": t_ref / t_ours, "speedup_coarse": t_ref / t_coarse, "transforms_alone_ms": t_floor,
              "share_same_top_peak": same_top, "share_same_top_peak_coarse": same_top_coarse}
    def row(name: str, label: str, floor: str | None) -> str:
        cells = [label, f"{ms[name]:.2f}", f"{cpu_ms[name]:.2f}", f"{t_ref / ms[name]:.1f}×", f"{ms[floor]:.2f}" if floor else ""]
        return "| " + " | ".join(cells) + " |"

    lines = ["# TDOA stage speed (GCC of all 15 pairs → 3 candidate peaks per pair), forest, 6 mics", "",
             f"`python benchmarks/bench_tdoa_stage.py --n-events {opts.n_events}`: {opts.n_events} simulated events, "
             f"{batch.audio.shape[-1]} samples per channel at {batch.sample_rate_hz:.0f} Hz; one process, one thread, batches of "
             f"{batch_events} events after a warm-up batch, the season loop's malloc settings (as `protocol=season` runs).", "",
             "| implementation | ms per event (wall) | CPU ms per event | speed-up | its transforms alone (ms per event) |", "|---|---|---|---|---|",
             row("reference", "reference (pair-wise weighting, double precision, full-length transforms)", None),
             row("acoustlab", "acoustlab `pair_candidates`", "transforms_alone_default"),
             row("acoustlab_coarse", "acoustlab, coarse search (`+features.gcc.search=coarse`)", "transforms_alone_coarse"), "",
             f"Same highest peak (within one lag step) on {100 * same_top:.1f} % of the pairs ({100 * same_top_coarse:.1f} % with the coarse "
             "search). Transforms alone: one single-precision forward transform per mic and one inverse transform per pair at the "
             "path's lengths, nothing else (the floor of each path on this machine)."]
    write_results("tdoa_stage", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
