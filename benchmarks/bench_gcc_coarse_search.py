"""The GCC's coarse search (``features.gcc.search=coarse``) against the default, on the first-stage inputs.

Usage: python benchmarks/bench_gcc_coarse_search.py [--sites forest frozen_lake] [--n-events 1100]

The default GCC (β-PHAT, 300–10,000 Hz, upsample 2, K = 3) inverse-transforms every pair's
cross-spectrum at twice the sampling rate (108,000 points for a 1.1-s clip at 24 kHz) and picks the
K highest local maxima of that grid. A 1/fs grid alone is 1.6× cheaper but was rejected
(docs/solvers.md): its parabolic heights reorder peaks whose band reaches near fs/2. The coarse
search (:mod:`acoustlab.toolkit.gcc_coarse`) transforms at fs, and refines the 16 highest local
maxima and the 16 highest maxima of two-sample sums of each window on the default's grid by
band-limited interpolation, ranking them as the default does.

On the same simulated events as the GPU benchmark (default simulator, 5 events per source
position), batches of 16, one process: ms per event of the TDOA stage for both; how far the
interpolated half-sample values lie from the default's exact ones; the share of pairs with the
same dominant lag (within 1 % of a fine lag step) and with the same K candidates; and the first
stage (default consistent-set solver reading the candidates and their heights only, the
pipeline's plausibility bound, failures as errors) on each: the share > 5 m with a 95 % interval
over source positions and the share of events whose fix is the same within 1 mm. The shipped LOCA
2021 recording's TDOAs (its 6–10.5 kHz band, where the plain 1/fs grid failed) are compared with
the upstream reference too.

Writes benchmarks/results/gcc_coarse_search.{json,md}.
"""

from __future__ import annotations

import argparse
import logging
import os
import time

import numpy as np
import pandas as pd
from bench_first_stage import share_ci
from bench_gcc_device import GROSS_M, SEASON_BATCH, simulate, slices, sub
from common import compose_cfg, machine, write_results

from acoustlab.core import columns as col
from acoustlab.core.types import RecordingBatch
from acoustlab.method.pipeline import error_2d_m
from acoustlab.reporting.metrics import error_summary
from acoustlab.run.registry import build
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import bound_fixes, solver_inputs_for
from acoustlab.toolkit.dsp import gcc
from acoustlab.toolkit.gcc_candidates import PairCandidates, lag_windows_s, pair_candidates
from acoustlab.toolkit.gcc_coarse import SEARCHED, TAPS, half_sample_kernel, half_samples

log = logging.getLogger("bench_gcc_coarse_search")
UPSTREAM_LOCA_TDOA_S = [0.0, 0.0325, -0.002, 0.0316, -0.0086, 0.024]  # tests/test_recordings.py


def timed(fn, batch: RecordingBatch) -> tuple[float, PairCandidates]:
    """ms per event of ``fn`` over the batch in season-sized batches, and its candidates."""
    fn(sub(batch, slice(0, SEASON_BATCH)))  # warm-up
    parts, start = [], time.perf_counter()
    for part in slices(batch.n_events, SEASON_BATCH):
        parts.append(fn(sub(batch, part)))
    ms = 1e3 * (time.perf_counter() - start) / batch.n_events
    return ms, PairCandidates(*(np.concatenate([getattr(c, f) for c in parts]) for f in ("lags_s", "heights", "sidelobe")))


def candidate_table(cands: PairCandidates, site) -> pd.DataFrame:
    """The tdoa and xcorr columns the solver reads, from candidates (as the feature groups write them)."""
    cols = {}
    for p, (i, j) in enumerate(site.mic_pairs):
        for k in range(cands.lags_s.shape[-1]):
            cols[col.tdoa_lag(i, j, k + 1)] = cands.lags_s[:, p, k]
            cols[col.xcorr_peak(i, j, k + 1)] = cands.heights[:, p, k]
    return pd.DataFrame(cols)


def fixes(cands: PairCandidates, batch: RecordingBatch, site, cfg, solver) -> tuple[dict, np.ndarray]:
    """First-stage errors (failures infinite) from candidates, and the fixes."""
    result = solver.solve(solver_inputs_for(candidate_table(cands, site), batch.events, site))
    position, _ = bound_fixes(result.position_m, site, float(cfg.pipeline.plausible_margin_fraction))
    err = error_2d_m(position, batch.events[["x_m", "y_m", "z_m"]].to_numpy(float))
    gross = ~(err <= GROSS_M)
    return {**error_summary(err), "share_gross": float(gross.mean()),
            "share_gross_ci95": share_ci(gross, batch.events["position_id"].to_numpy())}, position


def evaluate(site_name: str, n_events: int, n_jobs: int) -> dict:
    site, cfg, batch = simulate(site_name, n_events, n_jobs)
    g = cfg.features.gcc
    k, margin, band, weighting, beta = int(g.n_candidates), float(g.max_lag_margin_s), tuple(g.band_hz), str(g.weighting), float(g.beta)
    default_ms, ref = timed(lambda b: pair_candidates(b, site, k, margin, band, weighting, int(g.upsample), beta), batch)
    variant_ms, var = timed(lambda b: pair_candidates(b, site, k, margin, band, weighting, int(g.upsample), beta, search="coarse"), batch)
    step = 1.0 / (batch.sample_rate_hz * int(g.upsample))
    both_nan = np.isnan(ref.lags_s) & np.isnan(var.lags_s)
    same = (np.abs(ref.lags_s - var.lags_s) < 0.01 * step) | both_nan
    # interpolation error: the half-sample values against the default's exact odd samples, on a few events
    part = sub(batch, slice(0, SEASON_BATCH))
    windows = lag_windows_s(site, margin)
    fine, _ = gcc(part.audio, site.mic_pairs, batch.sample_rate_hz, weighting, band, 2, beta, max_lag_s=float(windows.max()))
    coarse, _ = gcc(part.audio, site.mic_pairs, batch.sample_rate_hz, weighting, band, 1, beta, max_lag_s=float(windows.max()))
    coarse *= np.float32(0.5)
    kernel = half_sample_kernel()
    n_coarse = coarse.shape[-1]
    idx = np.arange(kernel.size, n_coarse - kernel.size)
    errors = [np.abs(half_samples(coarse[:, p], np.broadcast_to(idx, (part.n_events, idx.size)), kernel) - fine[:, p, 2 * idx + 1]).max()
              / np.abs(fine[:, p]).max() for p in range(len(site.mic_pairs))]
    solver = build(compose_cfg([f"+site={site_name}"]).solver, "solver")
    first = {}
    positions = {}
    for name, cands in (("default", ref), ("coarse_search", var)):
        first[name], positions[name] = fixes(cands, batch, site, cfg, solver)
    a, b = positions["default"], positions["coarse_search"]
    same_fix = (np.hypot(*(a - b).T) < 1e-3) | (np.isnan(a).any(1) & np.isnan(b).any(1))
    log.info("%s: default %.2f ms, coarse search %.2f ms; same dominant lag %.4f", site_name, default_ms, variant_ms, same[..., 0].mean())
    return {"n_events": batch.n_events, "n_mics": site.n_mics, "tdoa_ms_per_event": {"default": default_ms, "coarse_search": variant_ms},
            "share_same_dominant_lag": float(same[..., 0].mean()), "share_same_k_candidates": float(same.all(-1).mean()),
            "max_interpolation_error_relative_to_peak": float(max(errors)), "first_stage": first,
            "share_same_fix_1mm": float(same_fix.mean())}


def loca_tdoas() -> dict:
    """Dominant TDOAs to mic 0 of the shipped LOCA 2021 recording (band 6–10.5 kHz), default and coarse search, against upstream's."""
    cfg = compose_cfg(["+site=loca2021", "field=recordings", "features.gcc.band_hz=[6000,10500]"])
    site = site_from_config(cfg.site)
    batch = build(cfg.field, "field").load(site)
    g = cfg.features.gcc
    args = (int(g.n_candidates), float(g.max_lag_margin_s), tuple(g.band_hz), str(g.weighting))
    ref = pair_candidates(batch, site, *args, int(g.upsample), float(g.beta))
    var = pair_candidates(RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events), site, *args, int(g.upsample), float(g.beta),
                          search="coarse")
    to_mic0 = [p for p, (i, _) in enumerate(site.mic_pairs) if i == 0]
    out = {"upstream": UPSTREAM_LOCA_TDOA_S}
    for name, c in (("default", ref), ("coarse_search", var)):
        out[name] = [0.0, *(float(c.lags_s[0, p, 0]) for p in to_mic0)]
        out[f"{name}_max_diff_from_upstream_s"] = float(np.max(np.abs(np.array(out[name]) - UPSTREAM_LOCA_TDOA_S)))
    return out


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["forest", "frozen_lake"])
    parser.add_argument("--n-events", type=int, default=1100)
    parser.add_argument("--n-jobs", type=int, default=os.cpu_count())
    opts = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sites = {s: evaluate(s, opts.n_events, opts.n_jobs) for s in opts.sites}
    loca = loca_tdoas()
    lines = ["# The GCC's coarse search: peaks searched on the 1/fs grid, refined on the 1/(2 fs) grid", "",
             f"`python benchmarks/bench_gcc_coarse_search.py --sites {' '.join(opts.sites)} --n-events {opts.n_events}`: "
             f"`+features.gcc.search=coarse` ({SEARCHED} + {SEARCHED} candidates refined per pair window, a {TAPS}-tap interpolation kernel; "
             "acoustlab/toolkit/gcc_coarse.py) against the default GCC (β-PHAT, 300–10,000 Hz, upsample 2, K = 3) on the same simulated events, "
             f"batches of {SEASON_BATCH}, one process; the first stage is the default consistent-set solver with the pipeline's "
             "plausibility bound, failures counted as errors.", "",
             "| site | TDOA stage, default (ms / event) | coarse search (ms / event) | speed-up | same dominant lag | same 3 candidates | "
             "interpolation error / peak | first stage > 5 m, default | coarse search | same fix (1 mm) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in sites.items():
        t, f = r["tdoa_ms_per_event"], r["first_stage"]
        cells = [f"{100 * f[v]['share_gross']:.2f} % ({100 * f[v]['share_gross_ci95'][0]:.1f}–{100 * f[v]['share_gross_ci95'][1]:.1f})"
                 for v in ("default", "coarse_search")]
        lines.append(f"| {name} ({r['n_mics']} mics, {r['n_events']} events) | {t['default']:.2f} | {t['coarse_search']:.2f} | "
                     f"{t['default'] / t['coarse_search']:.2f}× | {100 * r['share_same_dominant_lag']:.2f} % | "
                     f"{100 * r['share_same_k_candidates']:.2f} % | {r['max_interpolation_error_relative_to_peak']:.1e} | "
                     f"{cells[0]} | {cells[1]} | {100 * r['share_same_fix_1mm']:.2f} % |")
    lines += ["", "The shipped LOCA 2021 recording (band 6–10.5 kHz), dominant TDOAs to mic 0, s: upstream "
              f"{loca['upstream']}; default {[round(v, 5) for v in loca['default']]} (largest difference "
              f"{loca['default_max_diff_from_upstream_s'] * 1e3:.2f} ms); coarse search {[round(v, 5) for v in loca['coarse_search']]} "
              f"(largest difference {loca['coarse_search_max_diff_from_upstream_s'] * 1e3:.2f} ms)."]
    write_results("gcc_coarse_search", {"machine": machine(), "candidates_searched": SEARCHED, "taps": TAPS,
                                        "sites": sites, "loca2021": loca}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
