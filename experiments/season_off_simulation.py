"""The season's fast first stage (``+experiment=season_fast``) off the simulator it was fitted on, beside the defaults.

Usage: python experiments/season_off_simulation.py [--sites forest frozen_lake] [--n-positions 200]

``+experiment=season_fast`` (the lean feature set and the GCC's coarse peak search) was measured on this project's own simulation only (``lean_features``, ``season_search``).
Per site, three jobs of ``protocol=field_eval field=image_source`` with bench_cross_simulator.py's
method (XGBoost point model, XGBoost-quantile error model, learned gate, the paper's fixed and
GDOP-scaled conformal): each is fitted on 1,000 of the site's own simulated events and evaluated on
``--n-positions`` × 5 events rendered by an independent simulator (pyroomacoustics' image-source
method: sources in and around the array, SNR 5–30 dB, real calls and noise). The three differ only
in the first stage and the features: the defaults (``features=physics``), ``features=physics_lean``
and ``+experiment=season_fast``. Every job sees the same evaluation events, so the gated errors are
compared pairwise (a bootstrap over source positions, the report's ``relative_rows``), and the radii's
coverage beside them; then each configuration's errors and coverage inside and outside the site's
simulated source region (bench_cross_simulator.py's ``region_rows``). Failures count as infinite errors. Writes
experiments/results/season_off_simulation.md.
"""

from __future__ import annotations

import argparse
import logging
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import REPO, machine, write_results
from cross_simulator import METHOD, region_rows

from acoustlab.reporting.report import collect_runs, coverage_rows, error_rows, relative_rows

log = logging.getLogger("experiments.season_off_simulation")
#: The compared configurations, the reference first.
CONFIGS = {"defaults": [], "physics_lean": ["features=physics_lean"], "season_fast": ["+experiment=season_fast"]}


def site_runs(site: str, n_positions: int, folder: Path) -> tuple[list, dict[str, float]]:
    """The three jobs of one site (each a run folder under ``folder``), in ``CONFIGS``' order, and their wall times, s."""
    seconds = {}
    for name, extra in CONFIGS.items():
        args = [
            f"+site={site}",
            *METHOD,
            "protocol=field_eval",
            "field=image_source",
            f"field.n_positions={n_positions}",
            *extra,
            "tracking=none",
            "plots=false",
            f"hydra.run.dir={folder / name}",
        ]
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "acoustlab", *args], cwd=REPO, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"{site} {name} failed:\n{proc.stderr[-3000:]}")
        seconds[name] = time.perf_counter() - start
        log.info("%s %s: %.0f s", site, name, seconds[name])
    return collect_runs([folder / name for name in CONFIGS]), seconds


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["forest", "frozen_lake"])
    parser.add_argument("--n-positions", type=int, default=200, help="evaluation source positions per site (5 events each)")
    opts = parser.parse_args()
    result: dict = {"machine": machine(), "n_positions": opts.n_positions, "configs": CONFIGS, "sites": {}}
    lines = [
        "# The season's fast first stage off the simulator (`+experiment=season_fast`, beside the defaults)",
        "",
        f"`python experiments/season_off_simulation.py --sites {' '.join(opts.sites)} --n-positions {opts.n_positions}`: "
        "per site, fitted on 1,000 of the site's own simulated events, evaluated on "
        f"{5 * opts.n_positions:,} events rendered by pyroomacoustics' image-source method (`protocol=field_eval field=image_source`; "
        "XGBoost point model, XGBoost-quantile error model, learned gate, the paper's conformal). Configurations: defaults "
        "(`features=physics`, the default GCC search and solver), `features=physics_lean`, and `+experiment=season_fast` (the lean "
        "set with `features.gcc.search=coarse`). Failures are infinite errors; intervals are 95 % "
        "bootstraps over source positions.",
    ]
    for site in opts.sites:
        with tempfile.TemporaryDirectory() as tmp:
            runs, seconds = site_runs(site, opts.n_positions, Path(tmp))
            for run, name in zip(runs, CONFIGS):  # one label per configuration, whatever overrides tell them apart
                run.settings = {"configuration": name}
            errors = error_rows(runs)
            errors = errors[errors["method"].isin(["solver", "gate"])]
            relative, coverage = relative_rows(runs), coverage_rows(runs)
            regions = [row for name in CONFIGS for row in region_rows(site, name, Path(tmp) / name / "predictions.parquet")]
        result["sites"][site] = {
            "seconds": seconds,
            "errors": errors.to_dict("records"),
            "relative": relative.to_dict("records"),
            "coverage": coverage.to_dict("records"),
            "regions": regions,
        }
        keep = [
            c
            for c in errors.columns
            if c
            in ("configuration", "method", "n (detections)", "p50 (m)", "p90 (m)", "p95 (m)", "p99 (m)", "p95 95 % CI (m)", "> 5 m (%)")
        ]
        ckeep = [
            c
            for c in coverage.columns
            if c
            in (
                "configuration",
                "scorer",
                "coverage@0.5 (share)",
                "coverage@0.8 (share)",
                "coverage@0.95 (share)",
                "median radius@0.95 (m)",
                "worst position@0.95 (share)",
            )
        ]
        lines += [
            "",
            f"## {site} ({', '.join(f'{k} {v:.0f} s' for k, v in seconds.items())})",
            "",
            errors[keep].to_markdown(index=False, floatfmt=".3g"),
            "",
            "Gated error relative to the defaults (paired bootstrap over source positions; a configuration costs accuracy where "
            "an interval lies above 1):",
            "",
            relative.to_markdown(index=False, floatfmt=".3g"),
            "",
            "Coverage of the radii:",
            "",
            coverage[ckeep].to_markdown(index=False, floatfmt=".3g"),
            "",
            "By region (the site's simulated source region; the evaluation puts 30 % of its positions outside it): > 5 m % of "
            "solver / model / gate / gate_without_trust / gate_solver_only, and coverage of `fixed` at 0.50 / 0.80 / 0.95:",
            "",
            "| configuration | region (events) | > 5 m % | coverage |",
            "|---|---|---|---|",
            *regions,
        ]
    write_results("season_off_simulation", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
