"""Season-scale localize end to end: throughput, peak memory, accuracy, and sharded == unsharded.

A synthetic season (:mod:`acoustlab.season.synthetic`: calls rendered with numpy into long noise
files, one folder per recorder, files named by their start time, a Raven table per recorder) is
localized with ``python -m acoustlab season`` exactly as a user would: fit once, localize (one
process), merge; then again with ``--jobs`` local shards, whose positions must equal the
unsharded ones. Each localize runs in its own process, whose CPU time and peak RSS come from
``os.wait4``; the baseline RSS is the same command once every chunk is done (imports and the
fitted method, nothing computed).

Per-stage costs (reading, features, solver, method) are measured in this process on the first
chunks, beside a lean re-implementation of OpenSoundscape's approach (GCC-PHAT of every receiver
against the reference receiver within the array's largest delay, then SciPy least squares from
the receivers' centroid; OpenSoundscape itself is not installed here) on the same clips.

Usage::

    python benchmarks/bench_season.py --site forest --calls 500 2000 --jobs 4
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import scipy.optimize as so

from common import REPO, compose_cfg, fmt, machine, write_results

from acoustlab.method.saved import DIGEST_FILE, METHOD_FILE, load_method
from acoustlab.season.recorder_files import RecorderFiles
from acoustlab.season.stream import EVENTS, FILES, ChunkPlan, read_batch, read_manifest
from acoustlab.season.synthetic import SyntheticSeason, write_season
from acoustlab.stages.dataset import extract_features
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import add_solver_columns
from acoustlab.toolkit.dsp import gcc

log = logging.getLogger("bench_season")
WORK = REPO / "benchmarks" / "outputs" / "season"


def season_command(site: str, folder: Path, output_dir: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "acoustlab", "season", f"+site={site}", "tracking=none", "plots=false",
            f"protocol.recordings.audio_dir={folder / 'audio'}", f"protocol.detections.paths=[{folder / 'raven'}]",
            f"protocol.output_dir={output_dir}", f"hydra.run.dir={output_dir}_run", *extra]


#: Runs a command line as ``python -m acoustlab`` and reports the process' own peak RSS (VmHWM) at exit. The ``ru_maxrss`` of
#: ``os.wait4`` cannot serve: Linux carries the forking parent's high-water mark (this script renders gigabytes) into the child.
PEAK_PROBE = ("import atexit, runpy, sys; "
              "atexit.register(lambda: print('PEAK_RSS_KIB', next(l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM')), "
              "file=sys.stderr)); sys.argv = ['acoustlab', *sys.argv[1:]]; runpy.run_module('acoustlab', run_name='__main__')")


def measured(cmd: list[str]) -> dict[str, float]:
    """Run ``python -m acoustlab …`` (``cmd``); its wall time, CPU time (user + system, s, children included) and own peak RSS (MiB)."""
    assert cmd[1:3] == ["-m", "acoustlab"], cmd
    start = time.perf_counter()
    proc = subprocess.Popen([cmd[0], "-c", PEAK_PROBE, *cmd[3:]], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    output = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    if status != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{output[-3000:]}")
    peak = [line.split()[1] for line in output.splitlines() if line.startswith("PEAK_RSS_KIB")]
    return {"wall_s": time.perf_counter() - start, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mib": int(peak[-1]) / 1024}


#: How long before a call's arrival ``write_season``'s Raven selections begin, s.
RAVEN_PAD_S = 0.02


def truth_errors(positions: pd.DataFrame, events: pd.DataFrame, truth: pd.DataFrame, margin_s: float) -> dict[str, float]:
    """Errors of the placed positions against the rendered calls, each event matched to the call it holds.

    An event starts ``margin_s`` before its earliest selection, which begins ``RAVEN_PAD_S`` before
    the call's first arrival; so ``start_s + margin_s + RAVEN_PAD_S`` is that arrival, after the
    call's emission and (calls ≥ 2 s apart, travel < 0.5 s) before the next call's. Matching on
    ``start_s + margin_s`` alone, as this did before, took the previous call for every source
    within 0.02 s of travel (about 7 m) of its nearest recorder.
    """
    emission = truth["emission_s"].to_numpy()
    first_arrival = events["start_s"].to_numpy() + margin_s + RAVEN_PAD_S
    k = np.clip(np.searchsorted(emission, first_arrival, side="right") - 1, 0, len(truth) - 1)
    tx, ty = truth["x_m"].to_numpy()[k], truth["y_m"].to_numpy()[k]
    out = {}
    for name, (x, y) in {"method": ("x_m", "y_m"), "solver": ("solver_x_m", "solver_y_m")}.items():
        err = np.hypot(positions[x] - tx, positions[y] - ty).to_numpy()
        err = np.where(np.isfinite(err), err, np.inf)  # no position counts as an error
        out[name] = {"median_m": float(np.median(err)), "share_over_5m": float(np.mean(err > 5)), "share_over_10m": float(np.mean(err > 10))}
    err = np.hypot(positions["x_m"] - tx, positions["y_m"] - ty).to_numpy()
    placed = positions["placed"].to_numpy(bool)
    for level in ("0.5", "0.8", "0.95"):
        radius = positions[f"radius_gdop_scaled_{level}_m"].to_numpy(float)
        out[f"coverage_gdop_scaled_{level}"] = float(np.mean(err[placed] <= radius[placed])) if placed.any() else float("nan")
    out["n_matched_calls"] = int(np.unique(k).size)
    return out


def osl_style(audio: np.ndarray, mics: np.ndarray, fs: float, c: float, max_delay_s: float) -> np.ndarray:
    """OpenSoundscape's approach on one batch: GCC-PHAT against receiver 0 within ±max_delay, SciPy least squares from the centroid."""
    pairs = [(0, j) for j in range(1, mics.shape[0])]
    cc, lags = gcc(audio, pairs, fs, "phat", None, 1, max_lag_s=max_delay_s)
    window = np.abs(lags) <= max_delay_s
    tdoa = lags[window][np.argmax(cc[:, :, window], axis=-1)]  # (E, M-1): t_j - t_0
    out = np.empty((audio.shape[0], 2))
    for e in range(audio.shape[0]):
        def residual(p, e=e):
            d = np.sqrt(((p - mics[:, :2]) ** 2).sum(-1) + (mics[:, 2] - mics[:, 2].mean()) ** 2)
            return (d[1:] - d[0]) - c * tdoa[e]
        out[e] = so.least_squares(residual, mics[:, :2].mean(0)).x
    return out


def stage_costs(folder: Path, n_events: int) -> dict[str, float]:
    """ms per event of each stage on the first ``n_events`` events (one process, this machine), and the OpenSoundscape-style baseline."""
    manifest = read_manifest(folder)
    fitted = load_method(folder, manifest["method_sha256"])
    recordings = RecorderFiles.load(folder / FILES)
    events = pd.read_parquet(folder / EVENTS).iloc[:n_events]
    plan = ChunkPlan(manifest["chunk_events"], manifest["batch_events"])
    c = fitted.method.pipeline.c
    t = {"read": 0.0, "features": 0.0, "solver": 0.0, "method": 0.0, "opensoundscape_style": 0.0}
    features, rows = [], []
    speed = float(np.mean([331.3 * np.sqrt(1 + tc / 273.15) for tc in c.site.temperature_range_c]))
    mics = c.site.mic_positions_m
    max_delay = max(np.linalg.norm(mics[i] - mics[j]) for i, j in c.site.mic_pairs) / speed
    for first in range(0, len(events), plan.batch_events):
        start = time.process_time()
        batch = read_batch(recordings, events.iloc[first:first + plan.batch_events], manifest["recorders"], fitted.sample_rate_hz, plan)
        t["read"] += time.process_time() - start
        start = time.process_time()
        features.append(extract_features(batch, c.site, c.feature_sets))
        t["features"] += time.process_time() - start
        rows.append(batch.events)
        start = time.process_time()
        osl_style(batch.audio, mics, batch.sample_rate_hz, speed, max_delay)
        t["opensoundscape_style"] += time.process_time() - start
    table, detections = pd.concat(features, ignore_index=True), pd.concat(rows, ignore_index=True)
    start = time.process_time()
    table = add_solver_columns(table, detections, c.site, c.solver, fitted.plausible_margin_fraction)
    t["solver"] += time.process_time() - start
    start = time.process_time()
    fitted.method.predict(table, detections)
    t["method"] += time.process_time() - start
    return {k: 1000 * v / len(events) for k, v in t.items()}


def _vm(field: str) -> float:
    """This process' ``VmRSS`` or ``VmHWM`` in MiB."""
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith(field)) / 1024


def hwm_by_chunk(folder: Path, n: int) -> dict[str, list[float]]:
    """RSS and high-water mark (MiB) after each of the first ``n`` chunks, computed in this (fresh) process without writing parts."""
    from acoustlab.season.stream import localize_events, read_chunk

    manifest = read_manifest(folder)
    fitted = load_method(folder, manifest["method_sha256"])
    recordings = RecorderFiles.load(folder / FILES)
    plan = ChunkPlan(manifest["chunk_events"], manifest["batch_events"])
    out = {"start": [_vm("VmRSS"), _vm("VmHWM")], "rss": [], "hwm": []}
    for k in range(n):
        localize_events(fitted, recordings, read_chunk(folder, k, plan.chunk_events), manifest["recorders"], plan, recordings.origin)
        out["rss"].append(_vm("VmRSS"))
        out["hwm"].append(_vm("VmHWM"))
    return out


def bench_one(site_name: str, n_calls: int, jobs: int, file_s: float, method_from: Path | None) -> dict:
    cfg = compose_cfg([f"+site={site_name}"])
    site = site_from_config(cfg.site)
    settings = SyntheticSeason.for_site(site, duration_s=2.2 * n_calls + 5, file_s=file_s, n_calls=n_calls, min_spacing_s=2.0,
                                        sample_rate_hz=float(cfg.simulator.sample_rate_hz), seed=n_calls)
    folder = WORK / f"{site_name}_{n_calls}"
    if folder.exists():
        shutil.rmtree(folder)
    start = time.perf_counter()
    truth = write_season(settings, folder)
    render_s = time.perf_counter() - start
    out = folder / "season"
    if method_from is not None:  # the method fitted for the first season (same config): reused, verified by its digest
        out.mkdir(parents=True)
        for name in (METHOD_FILE, DIGEST_FILE):
            shutil.copy2(method_from / name, out / name)
    fit = measured(season_command(site_name, folder, out, "protocol.stage=fit"))
    unsharded = measured(season_command(site_name, folder, out, "protocol.stage=localize"))
    baseline = measured(season_command(site_name, folder, out, "protocol.stage=localize"))  # nothing left: imports + method
    merge = measured(season_command(site_name, folder, out, "protocol.stage=merge"))
    positions = pd.read_parquet(Path(f"{out}_run") / "positions.parquet")
    manifest = read_manifest(out)
    events = pd.read_parquet(out / EVENTS)
    audio_gib = sum(Path(p).stat().st_size for p in RecorderFiles.load(out / FILES).table["path"]) / 2**30
    sharded_dir = folder / "sharded"
    sharded_dir.mkdir()
    for name in (METHOD_FILE, DIGEST_FILE):
        shutil.copy2(out / name, sharded_dir / name)
    measured(season_command(site_name, folder, sharded_dir, "protocol.stage=fit"))
    sharded = measured(season_command(site_name, folder, sharded_dir, "protocol.stage=localize", f"protocol.n_jobs={jobs}"))
    measured(season_command(site_name, folder, sharded_dir, "protocol.stage=merge"))
    sharded_positions = pd.read_parquet(Path(f"{sharded_dir}_run") / "positions.parquet")
    identical = bool(positions.equals(sharded_positions))
    n_mics = site.n_mics
    clip_samples = ((events["end_s"] - events["start_s"]).max() * float(cfg.simulator.sample_rate_hz))
    batch_audio_mib = manifest["batch_events"] * n_mics * clip_samples * 4 / 2**20
    chunk_audio_mib = manifest["chunk_events"] * n_mics * clip_samples * 4 / 2**20  # what holding a chunk's clips would take
    from acoustlab.season.protocol import SeasonLocalize  # the margin the run used, for matching events to calls

    protocol = SeasonLocalize({}, {"format": "raven"}, {})
    return {
        "site": site_name, "n_calls": n_calls, "n_events": len(events), "recorders": n_mics, "audio_gib": audio_gib,
        "season_hours": settings.duration_s / 3600, "render_s": render_s, "fit": fit, "localize": unsharded, "baseline": baseline,
        "merge": merge, "sharded": sharded, "jobs": jobs, "sharded_identical": identical,
        "detections_per_s_cpu": len(events) / max(unsharded["cpu_s"] - baseline["cpu_s"], 1e-9),
        "detections_per_s_wall": len(events) / unsharded["wall_s"], "detections_per_s_sharded_wall": len(events) / sharded["wall_s"],
        "rss_above_baseline_mib": unsharded["peak_rss_mib"] - baseline["peak_rss_mib"], "batch_audio_mib": batch_audio_mib,
        "chunk_audio_mib": chunk_audio_mib,
        "chunk_events": manifest["chunk_events"], "batch_events": manifest["batch_events"],
        "accuracy": truth_errors(positions, events, truth, protocol.margin_s(site)),
        "stage_ms_per_event": stage_costs(out, min(len(events), 4 * manifest["batch_events"])),
        "memory_by_chunk_mib": json.loads(subprocess.run(
            [sys.executable, __file__, "--hwm-by-chunk", str(out), str(min(8, -(-len(events) // manifest["chunk_events"])))],
            cwd=REPO, capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]),
        "output_dir": str(out),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--site", default="forest")
    parser.add_argument("--calls", type=int, nargs="+", default=[500, 2000])
    parser.add_argument("--jobs", type=int, default=4, help="local shards compared with the unsharded run")
    parser.add_argument("--file-s", type=float, default=600.0, help="length of each recording file, s")
    parser.add_argument("--hwm-by-chunk", nargs=2, metavar=("FOLDER", "N"), help=argparse.SUPPRESS)  # internal: one fresh process
    args = parser.parse_args()
    if args.hwm_by_chunk:
        print(json.dumps(hwm_by_chunk(Path(args.hwm_by_chunk[0]), int(args.hwm_by_chunk[1]))))
        return
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    runs, method_from = [], None
    for n in args.calls:
        log.info("season of %d calls", n)
        runs.append(bench_one(args.site, n, args.jobs, args.file_s, method_from))
        method_from = Path(runs[-1]["output_dir"])
        log.info("%s", json.dumps(runs[-1], indent=1, default=float)[:2000])
    lines = [f"# Season-scale localize ({args.site})", "",
             f"`python benchmarks/bench_season.py --site {args.site} --calls {' '.join(map(str, args.calls))} --jobs {args.jobs} "
             f"--file-s {args.file_s:g}` ({machine()['cpus']} CPUs). Synthetic season: calls rendered into {args.file_s:g}-s files per "
             "recorder (named by start time), Raven tables per recorder, localized with `python -m acoustlab season` (its defaults: the lean "
             "feature set, the GCC's coarse search, the compiled solver). "
             "CPU time from `os.wait4`, peak RSS from the process' own VmHWM (the shards' workers are not in it); baseline = the same "
             "command with every chunk done (imports and the fitted method). The audio is read per batch of "
             f"{runs[0]['batch_events']} events; a chunk ({runs[0]['chunk_events']} events) is never held.", "",
             "| calls | events | audio (GiB) | detections/s (CPU) | detections/s (wall, 1 process) | "
             f"wall, {args.jobs} local shards | sharded == unsharded | peak RSS (MiB) | baseline | above baseline | one chunk's audio (MiB) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        lines.append(f"| {r['n_calls']} | {r['n_events']} | {r['audio_gib']:.2f} | {r['detections_per_s_cpu']:.1f} | {r['detections_per_s_wall']:.1f} | "
                     f"{r['detections_per_s_sharded_wall']:.1f}/s | {r['sharded_identical']} | {r['localize']['peak_rss_mib']:.0f} | "
                     f"{r['baseline']['peak_rss_mib']:.0f} | {r['rss_above_baseline_mib']:.0f} | {r['chunk_audio_mib']:.0f} |")
    lines += ["", "Accuracy against the rendered calls (no position counts as an error):", "",
              "| calls | method median (m) | method > 5 m | solver > 5 m | coverage (gdop_scaled) 0.50 / 0.80 / 0.95 |", "|---|---|---|---|---|"]
    for r in runs:
        a = r["accuracy"]
        lines.append(f"| {r['n_calls']} | {fmt(a['method']['median_m'])} | {a['method']['share_over_5m']:.1%} | "
                     f"{a['solver']['share_over_5m']:.1%} | {a['coverage_gdop_scaled_0.5']:.1%} / {a['coverage_gdop_scaled_0.8']:.1%} / "
                     f"{a['coverage_gdop_scaled_0.95']:.1%} |")
    for r in runs:
        m = r["memory_by_chunk_mib"]
        lines += ["", f"{r['n_calls']} calls, one fresh process chunk by chunk: high-water mark (MiB) after each chunk "
                  + ", ".join(f"{v:.0f}" for v in m["hwm"]) + f" (RSS {', '.join(f'{v:.0f}' for v in m['rss'])}; {m['start'][0]:.0f} at start)."]
    s = runs[-1]["stage_ms_per_event"]
    lines += ["", f"CPU ms per event by stage ({runs[-1]['n_calls']}-call season, first chunks, one process): "
              + ", ".join(f"{k} {v:.1f}" for k, v in s.items())
              + f". Ours in total {sum(v for k, v in s.items() if k != 'opensoundscape_style'):.1f} ms against "
              f"{s['opensoundscape_style']:.1f} ms for OpenSoundscape's approach (GCC-PHAT + SciPy least squares only: no features, "
              "no gate, no radii)."]
    write_results(f"season_{args.site}", {"machine": machine(), "runs": runs}, lines)


if __name__ == "__main__":
    main()
