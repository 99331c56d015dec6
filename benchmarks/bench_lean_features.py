"""``features=physics_lean`` against ``features=physics``, side by side in one run: CPU per detection and what the answer loses.

Usage: python benchmarks/bench_lean_features.py [--sites forest frozen_lake] [--n-folds 5] [--season-calls 2000] [--extra k=v ...]

Each measurement runs both feature sets on the same data:

1. **Feature stage**: process CPU ms per event of :func:`acoustlab.stages.dataset.extract_features`
   on 64 simulated events per site, the smallest of ``--repeats`` fresh batches, one process.
2. **The method, cross-fitted**: per site one sweep exactly as a user would run it
   (``python -m acoustlab -m +site=SITE features=physics,physics_lean protocol=cross_fit
   protocol.n_folds=N tracking=none plots=false``, default gate, error model and conformal
   scorers): every simulated event (``data.n_events``, 1,100 at 220 positions) is a test event once;
   gated and solver errors (failures count as errors), the lean job's gated percentiles relative to the
   full one with paired bootstrap intervals over source positions, and the coverage of the radii.
3. **A season end to end** (forest): one synthetic season rendered with numpy
   (:mod:`acoustlab.season.synthetic`, as ``bench_season.py``), fitted and localized with
   ``python -m acoustlab season`` once per feature set, both with the default GCC search and the numpy solver
   (``solver=consistent_set``; the season's own defaults add the coarse search and the compiled solver,
   ``bench_season_search.py``): detections/s of CPU (above the same
   command with nothing left to do), CPU ms per event by stage, and accuracy against the rendered
   calls.

Writes benchmarks/results/lean_features.{json,md}.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from bench_season import measured, season_command, stage_costs, truth_errors
from common import REPO, compose_cfg, fmt, machine, write_results

from acoustlab.core.types import RecordingBatch
from acoustlab.reporting.report import collect_runs, coverage_rows, error_rows, relative_rows
from acoustlab.run.registry import build, build_feature_sets
from acoustlab.season.stream import EVENTS
from acoustlab.season.synthetic import SyntheticSeason, write_season
from acoustlab.stages.dataset import extract_features
from acoustlab.stages.sites import site_from_config

log = logging.getLogger("bench_lean_features")
FEATURE_SETS = ("physics", "physics_lean")
WORK = REPO / "benchmarks" / "outputs" / "lean_features"


def feature_ms(site_name: str, n_events: int, repeats: int) -> dict[str, float]:
    """CPU ms per event of the whole feature stage with each feature set, on the same simulated events."""
    cfg = compose_cfg([f"+site={site_name}"])
    site = site_from_config(cfg.site)
    ids = np.arange(n_events)
    batch = build(cfg.simulator, "simulator").simulate(site, ids, ids // 5, 0)
    out = {}
    for name in FEATURE_SETS:
        sets = build_feature_sets(compose_cfg([f"+site={site_name}", f"features={name}"]).features)
        best = np.inf
        for _ in range(repeats):
            fresh = RecordingBatch(batch.audio, batch.sample_rate_hz, batch.events)  # nothing cached from the last repeat
            start = time.process_time()
            extract_features(fresh, site, sets)
            best = min(best, time.process_time() - start)
        out[name] = 1000 * best / n_events
    return out


def cross_fitted(site_name: str, n_folds: int, extra: list[str]) -> dict:
    """One sweep over both feature sets (``extra``: more overrides); the report's tables as records."""
    with tempfile.TemporaryDirectory() as tmp:
        args = ["-m", f"+site={site_name}", f"features={','.join(FEATURE_SETS)}", "protocol=cross_fit", f"protocol.n_folds={n_folds}",
                "tracking=none", "plots=false", *extra, f"paths.outputs_dir={tmp}", f"hydra.sweep.dir={tmp}/sweep"]
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "acoustlab", *args], cwd=REPO, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"sweep failed:\n{proc.stderr[-3000:]}")
        seconds = time.perf_counter() - start
        runs = collect_runs([Path(tmp) / "sweep"])
        errors = error_rows(runs)
        return {"seconds": seconds, "command": f"python -m acoustlab {' '.join(a for a in args if not a.startswith(('paths.', 'hydra.')))}",
                "errors": errors[errors["method"].isin(["gate", "solver"])].to_dict("records"),
                "relative": relative_rows(runs).to_dict("records"), "coverage": coverage_rows(runs).to_dict("records")}


def season(n_calls: int) -> dict:
    """A synthetic forest season fitted and localized with each feature set (same audio, same detections)."""
    from acoustlab.season.protocol import SeasonLocalize  # the margin a run uses to match events to calls

    cfg = compose_cfg(["+site=forest"])
    site = site_from_config(cfg.site)
    settings = SyntheticSeason.for_site(site, duration_s=2.2 * n_calls + 5, file_s=600.0, n_calls=n_calls, min_spacing_s=2.0,
                                        sample_rate_hz=float(cfg.simulator.sample_rate_hz), seed=n_calls)
    folder = WORK / f"forest_{n_calls}"
    if folder.exists():
        shutil.rmtree(folder)
    truth = write_season(settings, folder)
    margin_s = SeasonLocalize({}, {"format": "raven"}, {}).margin_s(site)
    out = {}
    for name in FEATURE_SETS:
        run = folder / name
        extra = [f"features={name}", "solver=consistent_set"]  # the feature set alone differs (not the season's coarse search and compiled solver)
        fit = measured(season_command("forest", folder, run, "protocol.stage=fit", *extra))
        localize = measured(season_command("forest", folder, run, "protocol.stage=localize", *extra))
        baseline = measured(season_command("forest", folder, run, "protocol.stage=localize", *extra))  # imports + the fitted method
        measured(season_command("forest", folder, run, "protocol.stage=merge", *extra))
        positions = pd.read_parquet(Path(f"{run}_run") / "positions.parquet")
        events = pd.read_parquet(run / EVENTS)
        out[name] = {"fit": fit, "localize": localize, "baseline": baseline, "n_events": len(events),
                     "detections_per_s_cpu": len(events) / max(localize["cpu_s"] - baseline["cpu_s"], 1e-9),
                     "accuracy": truth_errors(positions, events, truth, margin_s), "stage_ms_per_event": stage_costs(run, min(len(events), 64))}
    return out


def markdown(result: dict, opts: argparse.Namespace) -> list[str]:
    lines = ["# The lean feature set (features=physics_lean) against the full one (features=physics)", "",
             f"`python benchmarks/bench_lean_features.py --sites {' '.join(opts.sites)} --n-folds {opts.n_folds} --season-calls "
             f"{opts.season_calls} --repeats {opts.repeats}{' --extra ' + ' '.join(opts.extra) if opts.extra else ''}` ({machine()['cpus']} CPUs, one run). The lean set keeps the GCC groups "
             "(tdoa, xcorr in the main band, uncertainty) and the context groups; it leaves out ir, spectral, envelope and xcorr's "
             "extra 1–4 kHz band.", "", "## Feature stage, CPU ms per event (64 simulated events, smallest of the repeats)", "",
             "| site | physics | physics_lean | full / lean |", "|---|---|---|---|"]
    for site_name, ms in result["feature_ms"].items():
        lines.append(f"| {site_name} | {ms['physics']:.1f} | {ms['physics_lean']:.1f} | {ms['physics'] / ms['physics_lean']:.2f}× |")
    for site_name, sweep in result["cross_fitted"].items():
        errors = pd.DataFrame(sweep["errors"])
        keep = [c for c in errors.columns if c in ("features", "method", "n (detections)", "p50 (m)", "p90 (m)", "p95 (m)", "p99 (m)",
                                                   "p95 95 % CI (m)", "> 5 m (%)")]
        coverage = pd.DataFrame(sweep["coverage"])
        ckeep = [c for c in coverage.columns if c in ("features", "scorer", "coverage@0.8 (share)", "coverage@0.95 (share)",
                                                      "median radius@0.95 (m)", "worst position@0.95 (share)")]
        lines += ["", f"## {site_name}: the method cross-fitted ({sweep['seconds']:.0f} s)", "", f"`{sweep['command']}`", "",
                  errors[keep].to_markdown(index=False, floatfmt=".3g"), "",
                  "Lean relative to full, gated error (paired bootstrap over source positions; the lean set costs accuracy where "
                  "an interval lies above 1):", "", pd.DataFrame(sweep["relative"]).to_markdown(index=False, floatfmt=".3g"), "",
                  "Coverage of the radii:", "", coverage[ckeep].to_markdown(index=False, floatfmt=".3g")]
    if result.get("season"):
        lines += ["", f"## A forest season end to end ({opts.season_calls} calls, `python -m acoustlab season features=… solver=consistent_set`)", "",
                  "Both feature sets with the default GCC search and the numpy solver (the season's defaults, the lean set with the "
                  "coarse search and the compiled solver: `benchmarks/results/season_search.md`).", "",
                  "| features | events | detections/s (CPU) | fit CPU (s) | method median (m) | method > 5 m | solver > 5 m | "
                  "0.95 coverage (gdop_scaled) | CPU ms per event by stage | OpenSoundscape's approach (ms) |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for name, r in result["season"].items():
            a = r["accuracy"]
            stages = ", ".join(f"{k} {v:.1f}" for k, v in r["stage_ms_per_event"].items() if k != "opensoundscape_style")
            lines.append(f"| {name} | {r['n_events']} | {r['detections_per_s_cpu']:.1f} | {r['fit']['cpu_s']:.0f} | "
                         f"{fmt(a['method']['median_m'])} | {a['method']['share_over_5m']:.1%} | {a['solver']['share_over_5m']:.1%} | "
                         f"{a['coverage_gdop_scaled_0.95']:.1%} | {stages} | {r['stage_ms_per_event']['opensoundscape_style']:.1f} |")
        s = result["season"]
        lines += ["", f"Lean over full, detections/s of CPU: {s['physics_lean']['detections_per_s_cpu'] / s['physics']['detections_per_s_cpu']:.2f}×. "
                  "Stage costs are measured in this process on the season's first 64 events, beside bench_season.py's lean "
                  "re-implementation of OpenSoundscape's approach (GCC-PHAT against one receiver, SciPy least squares; no features, "
                  "no gate, no radii) on the same clips."]
    return lines


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["forest", "frozen_lake"])
    parser.add_argument("--n-folds", type=int, default=5)
    parser.add_argument("--season-calls", type=int, default=2000, help="calls in the forest season (0: no season)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--extra", nargs="*", default=[], help="more overrides for the cross-fitted sweeps")
    opts = parser.parse_args()
    result: dict = {"machine": machine(), "feature_ms": {}, "cross_fitted": {}}
    for site_name in opts.sites:
        result["feature_ms"][site_name] = feature_ms(site_name, 64, opts.repeats)
        log.info("%s feature ms per event: %s", site_name, result["feature_ms"][site_name])
    if opts.season_calls:
        result["season"] = season(opts.season_calls)
        log.info("season: %s", {k: v["detections_per_s_cpu"] for k, v in result["season"].items()})
    for site_name in opts.sites:
        result["cross_fitted"][site_name] = cross_fitted(site_name, opts.n_folds, opts.extra)
        log.info("%s cross-fitted in %.0f s", site_name, result["cross_fitted"][site_name]["seconds"])
    lines = markdown(result, opts)
    write_results("lean_features", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
