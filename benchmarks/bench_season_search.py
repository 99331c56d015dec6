"""A season localized end to end with the GCC's coarse search against the default search, and with the compiled solver: one run, one machine, CPU only.

Usage: python benchmarks/bench_season_search.py [--site forest] [--calls 2000]

Renders one synthetic season with ``bench_season.py``'s settings (calls rendered into long noise
files per recorder, Raven tables per recorder), then for ``features=physics_lean solver=consistent_set``
(the default GCC search and the numpy solver), the same with ``+features.gcc.search=coarse``
(:mod:`acoustlab.toolkit.gcc_coarse`) and the season's defaults, which add ``solver=consistent_set_compiled``
(:mod:`plugins.solvers.consistent_set_compiled`; the three together, also ``+experiment=season_fast``: a test checks
that the season composes to exactly them): fits the method once,
localizes every detection in one process, runs the same command again with nothing left to do (the
baseline), merges, and scores the positions against the rendered calls (``bench_season_device``'s
steps). Detections per second of wall time and of CPU time, above the baseline. Then the same
fitted method localizes the season again in ``--jobs`` local shards (``protocol.n_jobs``): the
wall-time rate on this machine's cores, and whether the positions equal the unsharded ones. Writes
benchmarks/results/season_search.{json,md}.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time
from pathlib import Path

import numpy as np
import pandas as pd
from bench_season import WORK, measured, season_command
from bench_season_device import run_config
from common import compose_cfg, machine, write_results

from acoustlab.method.saved import DIGEST_FILE, METHOD_FILE
from acoustlab.season.protocol import SeasonLocalize
from acoustlab.season.synthetic import SyntheticSeason, write_season
from acoustlab.stages.sites import site_from_config

log = logging.getLogger("bench_season_search")


def sharded(site_name: str, folder: Path, name: str, overrides: list[str], jobs: int, n_events: int) -> dict:
    """Localize again with the method ``run_config`` fitted, in ``jobs`` local shards: wall-time rates and sharded == unsharded."""
    fitted, out = folder / f"season_{name}", folder / f"season_{name}_sharded"
    out.mkdir()
    for file in (METHOD_FILE, DIGEST_FILE):
        shutil.copy2(fitted / file, out / file)
    command = lambda *extra: season_command(site_name, folder, out, *overrides, *extra)  # noqa: E731
    measured(command("protocol.stage=fit"))  # finds the method: plans the chunks only
    run = measured(command("protocol.stage=localize", f"protocol.n_jobs={jobs}"))
    baseline = measured(command("protocol.stage=localize", f"protocol.n_jobs={jobs}"))
    measured(command("protocol.stage=merge"))
    same = pd.read_parquet(Path(f"{out}_run") / "positions.parquet").equals(pd.read_parquet(Path(f"{fitted}_run") / "positions.parquet"))
    return {"jobs": jobs, "localize": run, "baseline": baseline, "detections_per_s_wall": n_events / run["wall_s"],
            "detections_per_s_wall_above_baseline": n_events / max(run["wall_s"] - baseline["wall_s"], 1e-9), "identical_to_unsharded": bool(same)}


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--site", default="forest")
    parser.add_argument("--calls", type=int, default=2000)
    parser.add_argument("--file-s", type=float, default=600.0)
    parser.add_argument("--jobs", type=int, default=2, help="local shards of the second localize")
    opts = parser.parse_args()
    cfg = compose_cfg([f"+site={opts.site}"])
    site = site_from_config(cfg.site)
    settings = SyntheticSeason.for_site(site, duration_s=2.2 * opts.calls + 5, file_s=opts.file_s, n_calls=opts.calls, min_spacing_s=2.0,
                                        sample_rate_hz=float(cfg.simulator.sample_rate_hz), seed=opts.calls)
    folder = WORK / f"search_{opts.site}_{opts.calls}"
    if folder.exists():
        shutil.rmtree(folder)
    start = time.perf_counter()
    truth = write_season(settings, folder)
    render_s = time.perf_counter() - start
    margin_s = SeasonLocalize({}, {"format": "raven"}, {}).margin_s(site)
    configs = {"fine": ["features=physics_lean", "solver=consistent_set"],
               "coarse": ["features=physics_lean", "+features.gcc.search=coarse", "solver=consistent_set"],
               "coarse_compiled": []}  # the season's defaults: features=physics_lean_coarse solver=consistent_set_compiled
    rows = {name: run_config(opts.site, folder, name, overrides, truth, margin_s) for name, overrides in configs.items()}
    for name, overrides in configs.items():
        rows[name]["sharded"] = sharded(opts.site, folder, name, overrides, opts.jobs, rows[name]["n_events"])
    numpy_fix, compiled_fix = (pd.read_parquet(Path(f"{folder / f'season_{name}'}_run") / "positions.parquet") for name in ("coarse", "coarse_compiled"))
    solver_difference_m = float(np.nanmax(np.hypot(numpy_fix["solver_x_m"] - compiled_fix["solver_x_m"], numpy_fix["solver_y_m"] - compiled_fix["solver_y_m"])))
    same_failures = bool((numpy_fix["solver_x_m"].isna() == compiled_fix["solver_x_m"].isna()).all())
    lines = ["# A season end to end with the GCC's coarse search against the default (one run, one machine, CPU)", "",
             f"`python benchmarks/bench_season_search.py --site {opts.site} --calls {opts.calls} --jobs {opts.jobs}`: a synthetic {opts.site} season of "
             f"{opts.calls} calls ({settings.duration_s / 3600:.2f} h, rendered in {render_s:.0f} s), `python -m acoustlab season` with "
             f"the lean feature set, one localizing process, {machine()['cpus']} CPU cores; the method fitted once per search. "
             "Rates are above the baseline (the same command with every chunk done).", "",
             "| configuration | detections | detections/s (wall) | detections/s (CPU) | fit (wall, s) | method > 5 m | solver > 5 m | "
             f"GDOP-scaled 0.95 radii cover | {opts.jobs} local shards: detections/s (wall; above baseline) | sharded == unsharded |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        acc = r["accuracy"]
        lines.append(f"| {name} | {r['n_events']} | {r['detections_per_s_wall']:.1f} | {r['detections_per_s_cpu']:.1f} | "
                     f"{r['fit']['wall_s']:.0f} | {100 * acc['method']['share_over_5m']:.1f} % | {100 * acc['solver']['share_over_5m']:.1f} % | "
                     f"{100 * acc['coverage_gdop_scaled_0.95']:.1f} % | {r['sharded']['detections_per_s_wall']:.1f} "
                     f"({r['sharded']['detections_per_s_wall_above_baseline']:.1f}) | {r['sharded']['identical_to_unsharded']} |")
    fine, coarse, compiled = rows["fine"], rows["coarse"], rows["coarse_compiled"]
    lines += ["", "Configurations: fine = `features=physics_lean solver=consistent_set` (the default GCC search, the numpy solver); "
              "coarse = the same with `+features.gcc.search=coarse`; coarse_compiled = the season's defaults (no overrides: "
              "`features=physics_lean_coarse solver=consistent_set_compiled`, coarse with the compiled solver, fitted with it too; "
              "the same as `+experiment=season_fast`).", "",
              f"CPU per detection: the coarse search's rate is {coarse['detections_per_s_cpu'] / fine['detections_per_s_cpu']:.2f}× "
              f"the default search's; the compiled solver's {compiled['detections_per_s_cpu'] / coarse['detections_per_s_cpu']:.2f}× coarse's. "
              f"Solver positions, coarse against coarse_compiled: largest difference {solver_difference_m:.2g} m, "
              f"{'the same' if same_failures else 'NOT the same'} detections without a fix."]
    write_results("season_search", {"machine": machine(), "site": opts.site, "calls": opts.calls, "render_s": render_s, "configs": rows,
                                    "solver_position_difference_m": solver_difference_m, "same_detections_without_fix": same_failures}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
