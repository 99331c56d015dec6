"""The GCC on a GPU (``+features.gcc.device=cuda``) against the CPU path, side by side in one run, on one machine.

Usage (on a machine with a CUDA GPU and torch)::

    python benchmarks/bench_gcc_device.py [--sites forest frozen_lake] [--n-events 1100] [--batch-sizes 16 64 256]

For every site, the same freshly simulated events (default simulator, source positions of 5 events
each, rendered in parallel) go through:

* **the TDOA stage** (:func:`acoustlab.toolkit.gcc_candidates.pair_candidates`, default GCC
  settings: β-PHAT, 300–10,000 Hz, upsample 2, K = 3), on the CPU (numpy/SciPy, one process, one
  thread) in batches of 16 events as a season computes them, and with torch on the GPU in batches
  of each ``--batch-sizes`` (the device synchronised by copying the peaks back);
* **the lean feature stage** (``features=physics_lean``, what a season computes per detection) in
  batches of 16, CPU against GPU;
* **the first stage** on each path's features: the default consistent-set solver, the plausibility
  bound of the pipeline, errors with failures as infinite; the share > 5 m with a 95 % bootstrap
  interval over source positions, the share of pairs whose dominant lag is the same (within 1 % of a
  lag step) and the share of events whose fix is the same within 1 mm.

The CPU figures are the GPU machine's own CPU (one core), so the ratio is measured on one machine;
compare them with other results only through the ratio. Writes
benchmarks/results/gcc_device.{json,md}.
"""

from __future__ import annotations

import argparse
import logging
import os
import time

import numpy as np
import pandas as pd
from bench_first_stage import share_ci
from common import compose_cfg, machine, write_results

from acoustlab.core.types import RecordingBatch
from acoustlab.method.pipeline import error_2d_m
from acoustlab.reporting.metrics import error_summary
from acoustlab.run.registry import build, build_feature_sets
from acoustlab.stages.dataset import extract_features
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import bound_fixes, solver_inputs_for
from acoustlab.toolkit.gcc_candidates import pair_candidates

log = logging.getLogger("bench_gcc_device")
SEASON_BATCH = 16
GROSS_M = 5.0


def simulate(site_name: str, n_events: int, n_jobs: int) -> tuple:
    """Site, config and the simulated batches (chunks of 64 events, 5 events per source position)."""
    from joblib import Parallel, delayed

    cfg = compose_cfg([f"+site={site_name}", "features=physics_lean"])
    site = site_from_config(cfg.site)
    simulator = build(cfg.simulator, "simulator")
    starts = range(0, n_events, 64)

    def one(start: int) -> RecordingBatch:
        ids = np.arange(start, min(start + 64, n_events))
        return simulator.simulate(site, ids, ids // 5, int(cfg.seed))

    batches = Parallel(n_jobs=n_jobs)(delayed(one)(s) for s in starts)
    audio = np.concatenate([b.audio for b in batches])
    events = pd.concat([b.events for b in batches], ignore_index=True)
    return site, cfg, RecordingBatch(audio, batches[0].sample_rate_hz, events)


def slices(n: int, size: int) -> list[slice]:
    return [slice(s, min(s + size, n)) for s in range(0, n, size)]


def sub(batch: RecordingBatch, part: slice) -> RecordingBatch:
    """A fresh batch (nothing derived cached) of some events."""
    return RecordingBatch(batch.audio[part], batch.sample_rate_hz, batch.events.iloc[part].reset_index(drop=True))


def tdoa_stage(batch: RecordingBatch, site, gcc, device: str, size: int) -> tuple[float, np.ndarray]:
    """ms per event of pair_candidates over every event in batches of ``size``, and the dominant lags (E, P)."""
    args = (site, int(gcc.n_candidates), float(gcc.max_lag_margin_s), tuple(gcc.band_hz), str(gcc.weighting), int(gcc.upsample),
            float(gcc.beta))
    pair_candidates(sub(batch, slice(0, size)), *args, device=device)  # warm-up (cuFFT plans, allocator)
    top, start = [], time.perf_counter()
    for part in slices(batch.n_events, size):
        top.append(pair_candidates(sub(batch, part), *args, device=device).lags_s[..., 0])
    return 1e3 * (time.perf_counter() - start) / batch.n_events, np.concatenate(top)


def feature_stage(batch: RecordingBatch, site, features_cfg) -> tuple[float, pd.DataFrame]:
    """ms per event of the lean feature stage in batches of a season's size, and the table."""
    sets = build_feature_sets(features_cfg)
    extract_features(sub(batch, slice(0, SEASON_BATCH)), site, sets)  # warm-up
    start = time.perf_counter()
    table = pd.concat([extract_features(sub(batch, part), site, sets) for part in slices(batch.n_events, SEASON_BATCH)], ignore_index=True)
    return 1e3 * (time.perf_counter() - start) / batch.n_events, table


def first_stage(table: pd.DataFrame, batch: RecordingBatch, site, cfg, solver) -> dict:
    """Errors of the default solver on one feature table (failures infinite)."""
    result = solver.solve(solver_inputs_for(table, batch.events, site))
    position, _ = bound_fixes(result.position_m, site, float(cfg.pipeline.plausible_margin_fraction))
    truth = batch.events[["x_m", "y_m", "z_m"]].to_numpy(float)
    err = error_2d_m(position, truth)
    gross = ~(err <= GROSS_M)
    return {**error_summary(err), "share_gross": float(gross.mean()), "share_gross_ci95": share_ci(gross, batch.events["position_id"].to_numpy()),
            "position": position}


def evaluate(site_name: str, n_events: int, batch_sizes: list[int], device: str, n_jobs: int) -> dict:
    import torch

    start = time.perf_counter()
    site, cfg, batch = simulate(site_name, n_events, n_jobs)
    log.info("%s: %d events simulated in %.0f s", site_name, batch.n_events, time.perf_counter() - start)
    gcc = cfg.features.gcc
    out: dict = {"n_events": batch.n_events, "n_mics": site.n_mics, "samples_per_channel": int(batch.audio.shape[-1]),
                 "sample_rate_hz": batch.sample_rate_hz,
                 "gpu": torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda") else "none"}
    cpu_ms, cpu_top = tdoa_stage(batch, site, gcc, "cpu", SEASON_BATCH)
    out["tdoa_ms_per_event"] = {"cpu": cpu_ms}
    step = 1.0 / (batch.sample_rate_hz * int(gcc.upsample))
    for size in batch_sizes:
        ms, top = tdoa_stage(batch, site, gcc, device, size)
        out["tdoa_ms_per_event"][f"{device}_batch_{size}"] = ms
        same = np.abs(top - cpu_top) < 0.01 * step
        out.setdefault("share_same_dominant_lag", {})[str(size)] = float(np.mean(same | (np.isnan(top) & np.isnan(cpu_top))))
        log.info("%s TDOA stage: CPU %.2f ms/event, %s (batch %d) %.3f ms/event", site_name, cpu_ms, device, size, ms)
    solver = build(compose_cfg([f"+site={site_name}"]).solver, "solver")
    gpu_features_cfg = compose_cfg([f"+site={site_name}", "features=physics_lean", f"+features.gcc.device={device}"]).features
    stages = {"cpu": cfg.features, device: gpu_features_cfg}
    positions = {}
    for name, features_cfg in stages.items():
        ms, table = feature_stage(batch, site, features_cfg)
        res = first_stage(table, batch, site, cfg, solver)
        positions[name] = res.pop("position")
        out.setdefault("lean_features_ms_per_event", {})[name] = ms
        out.setdefault("first_stage", {})[name] = res
        log.info("%s %s: lean features %.2f ms/event; > 5 m %.2f %%", site_name, name, ms, 100 * res["share_gross"])
    a, b = positions["cpu"], positions[device]
    same_fix = (np.hypot(*(a - b).T) < 1e-3) | (np.isnan(a).any(1) & np.isnan(b).any(1))
    out["share_same_fix_1mm"] = float(same_fix.mean())
    return out


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["forest", "frozen_lake"])
    parser.add_argument("--n-events", type=int, default=1100)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--n-jobs", type=int, default=os.cpu_count())
    opts = parser.parse_args()
    sites = {s: evaluate(s, opts.n_events, opts.batch_sizes, opts.device, opts.n_jobs) for s in opts.sites}
    dev = opts.device
    first = next(iter(sites.values()))
    lines = ["# The GCC on a GPU against the CPU path (one run, one machine)", "",
             f"`python benchmarks/bench_gcc_device.py --sites {' '.join(opts.sites)} --n-events {opts.n_events} "
             f"--batch-sizes {' '.join(map(str, opts.batch_sizes))}`; GPU: {first['gpu']}; CPU: the same machine's, one process. "
             "Default GCC settings (β-PHAT, 300–10,000 Hz, upsample 2, K = 3); the first stage is the default consistent-set solver "
             "with the pipeline's plausibility bound, failures counted as errors.", ""]
    for site_name, r in sites.items():
        cpu_ms = r["tdoa_ms_per_event"]["cpu"]
        lines += [f"## {site_name}: {r['n_events']} events, {r['n_mics']} mics, {r['samples_per_channel']} samples per channel "
                  f"at {r['sample_rate_hz']:.0f} Hz", "",
                  "| TDOA stage | ms per event | speed-up over the CPU | same dominant lag as the CPU |", "|---|---|---|---|",
                  f"| CPU (numpy/SciPy), batches of {SEASON_BATCH} | {cpu_ms:.2f} | 1.0× | — |"]
        for size in opts.batch_sizes:
            ms = r["tdoa_ms_per_event"][f"{dev}_batch_{size}"]
            lines.append(f"| {dev} (torch), batches of {size} | {ms:.3f} | {cpu_ms / ms:.1f}× | "
                         f"{100 * r['share_same_dominant_lag'][str(size)]:.2f} % of pairs |")
        fs = r["lean_features_ms_per_event"]
        lines += ["", "| features=physics_lean, batches of 16 | ms per event | p50 (m) | p95 (m) | first stage > 5 m (95 % CI by position) |",
                  "|---|---|---|---|---|"]
        for name in ("cpu", dev):
            f = r["first_stage"][name]
            lo, hi = f["share_gross_ci95"]
            lines.append(f"| {name} | {fs[name]:.2f} | {f['p50']:.2f} | {f['p95']:.2f} | {100 * f['share_gross']:.2f} % ({100 * lo:.1f}–{100 * hi:.1f}) |")
        lines += ["", f"Feature stage {fs['cpu'] / fs[dev]:.1f}× faster on the GPU; the same solver fix (within 1 mm) for "
                  f"{100 * r['share_same_fix_1mm']:.2f} % of events.", ""]
    write_results("gcc_device", {"machine": machine(), "device": dev, "sites": sites}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
