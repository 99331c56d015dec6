"""``features=physics_lean`` against ``features=physics``, cross-fitted side by side in one run: what the lean set costs the answer.

Usage: python experiments/lean_features.py [--sites forest frozen_lake] [--n-folds 5] [--extra k=v ...]

Per site one sweep exactly as a user would run it (``python -m acoustlab -m +site=SITE
features=physics,physics_lean protocol=cross_fit protocol.n_folds=N tracking=none plots=false``,
default gate, error model and conformal scorers): every simulated event (``data.n_events``, 1,100 at
220 positions) is a test event once; gated and solver errors (failures count as errors), the lean
job's gated percentiles relative to the full one with paired bootstrap intervals over source
positions, and the coverage of the radii. What the lean set saves in time is a speed benchmark:
``python benchmarks/run.py features season``.

Writes experiments/results/lean_features.md.
"""

from __future__ import annotations

import argparse
import logging
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
from common import REPO, machine, write_results

from acoustlab.reporting.report import collect_runs, coverage_rows, error_rows, relative_rows

log = logging.getLogger("experiments.lean_features")
FEATURE_SETS = ("physics", "physics_lean")


def cross_fitted(site_name: str, n_folds: int, extra: list[str]) -> dict:
    """One sweep over both feature sets (``extra``: more overrides); the report's tables as records."""
    with tempfile.TemporaryDirectory() as tmp:
        args = [
            "-m",
            f"+site={site_name}",
            f"features={','.join(FEATURE_SETS)}",
            "protocol=cross_fit",
            f"protocol.n_folds={n_folds}",
            "tracking=none",
            "plots=false",
            *extra,
            f"paths.outputs_dir={tmp}",
            f"hydra.sweep.dir={tmp}/sweep",
        ]
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "acoustlab", *args], cwd=REPO, capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"sweep failed:\n{proc.stderr[-3000:]}")
        seconds = time.perf_counter() - start
        runs = collect_runs([Path(tmp) / "sweep"])
        errors = error_rows(runs)
        return {
            "seconds": seconds,
            "command": f"python -m acoustlab {' '.join(a for a in args if not a.startswith(('paths.', 'hydra.')))}",
            "errors": errors[errors["method"].isin(["gate", "solver"])].to_dict("records"),
            "relative": relative_rows(runs).to_dict("records"),
            "coverage": coverage_rows(runs).to_dict("records"),
        }


def markdown(result: dict, opts: argparse.Namespace) -> list[str]:
    lines = [
        "# The lean feature set (features=physics_lean) against the full one (features=physics)",
        "",
        f"{machine()['cpus']} CPUs, one run. The lean set keeps the GCC groups "
        "(tdoa, xcorr in the main band, uncertainty) and the context groups; it leaves out ir, spectral, envelope and xcorr's "
        "extra 1–4 kHz band. Its speed: `python benchmarks/run.py features season`.",
    ]
    for site_name, sweep in result["cross_fitted"].items():
        errors = pd.DataFrame(sweep["errors"])
        keep = [
            c
            for c in errors.columns
            if c in ("features", "method", "n (detections)", "p50 (m)", "p90 (m)", "p95 (m)", "p99 (m)", "p95 95 % CI (m)", "> 5 m (%)")
        ]
        coverage = pd.DataFrame(sweep["coverage"])
        ckeep = [
            c
            for c in coverage.columns
            if c
            in (
                "features",
                "scorer",
                "coverage@0.8 (share)",
                "coverage@0.95 (share)",
                "median radius@0.95 (m)",
                "worst position@0.95 (share)",
            )
        ]
        lines += [
            "",
            f"## {site_name}: the method cross-fitted ({sweep['seconds']:.0f} s)",
            "",
            f"`{sweep['command']}`",
            "",
            errors[keep].to_markdown(index=False, floatfmt=".3g"),
            "",
            "Lean relative to full, gated error (paired bootstrap over source positions; the lean set costs accuracy where "
            "an interval lies above 1):",
            "",
            pd.DataFrame(sweep["relative"]).to_markdown(index=False, floatfmt=".3g"),
            "",
            "Coverage of the radii:",
            "",
            coverage[ckeep].to_markdown(index=False, floatfmt=".3g"),
        ]
    return lines


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["forest", "frozen_lake"])
    parser.add_argument("--n-folds", type=int, default=5)
    parser.add_argument("--extra", nargs="*", default=[], help="more overrides for the cross-fitted sweeps")
    opts = parser.parse_args()
    result: dict = {"machine": machine(), "cross_fitted": {}}
    for site_name in opts.sites:
        result["cross_fitted"][site_name] = cross_fitted(site_name, opts.n_folds, opts.extra)
        log.info("%s cross-fitted in %.0f s", site_name, result["cross_fitted"][site_name]["seconds"])
    lines = markdown(result, opts)
    write_results("lean_features", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
