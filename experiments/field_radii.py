"""Do radii hold at a site after calibrating them on a few playback spots? Second simulator, held out by position.

Usage: python experiments/field_radii.py [--sites frozen_lake forest] [--spots 10 20] [--n-positions 60]

Per site: the method (XGBoost point model, XGBoost-quantile error model, learned gate, the paper's
fixed and GDOP-scaled conformal) trained on 1,000 events of acoustlab's simulator, evaluated on
recordings rendered by pyroomacoustics (``field=image_source``, ``--n-positions`` × 5 events, 30 %
of the positions outside the simulated region):

* **without calibration**: radii calibrated on the simulation (``protocol=field_eval``);
* **with K spots**: K of the field positions drawn at random are playback spots
  (``protocol.calibration_positions=K``): they join training and calibrate the radii at the
  position level; the other positions are the test.

Coverage is reported per detection and per position (the mean over test positions of the share of
their detections covered), with the median radius beside the oracle radius (the level-quantile of
the test errors themselves: what a radius calibrated on the test could be). Writes
experiments/results/field_radii.md.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
import pandas as pd
from common import REPO, fmt, machine, run_in_process, write_results

log = logging.getLogger("experiments.field_radii")
METHOD = ["model=xgboost", "error_model=xgboost_quantile", "gate=learned", "conformal=paper"]
LEVELS = ("0.5", "0.8", "0.95")
SCORERS = ("fixed", "gdop_scaled")
#: the runs' predictions (git-ignored)
KEPT = REPO / "outputs" / "bench_field_radii"


def coverage_cells(m: dict, scorer: str) -> str:
    by_position = m["coverage_by_position"][scorer]
    cells = []
    for lv in LEVELS:
        detection = m["coverage"][scorer][lv]
        position = by_position[lv]["mean"]
        cells.append("—" if detection != detection else f"{detection:.2f} / {position:.2f}")
    return " | ".join(cells)


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["frozen_lake", "forest"])
    parser.add_argument("--spots", nargs="+", type=int, default=[10, 20])
    parser.add_argument("--n-positions", type=int, default=60)
    opts = parser.parse_args()
    lines = [
        "# Radii at a site, calibrated on playback spots (second simulator, held out by position)",
        "",
        f"`python experiments/field_radii.py --sites {' '.join(opts.sites)} --spots {' '.join(map(str, opts.spots))} "
        f"--n-positions {opts.n_positions}`. Coverage per detection / per position (mean over test positions) at 0.50, 0.80 "
        "and 0.95; '—' where the spots cannot support the level (no radius). Oracle: the level-quantile of the test errors.",
        "",
        "| site | radii calibrated on | scorer | 0.50 | 0.80 | 0.95 | median 0.80 radius (m) | oracle 0.80 (m) | test events |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    raw: dict[str, dict] = {}
    for site in opts.sites:
        base = [f"+site={site}", *METHOD, "protocol=field_eval", "field=image_source", f"field.n_positions={opts.n_positions}"]
        for spots in [0, *opts.spots]:
            label = "the simulation" if spots == 0 else f"{spots} field spots"
            kept = KEPT / f"{site}_{spots}.parquet"
            m = run_in_process([*base, f"protocol.calibration_positions={spots}"], kept)
            gate = m["errors"]["gate"]
            test_errors = pd.read_parquet(kept)["error_gate_m"].to_numpy(float)
            raw[f"{site}/{spots}"] = {
                "coverage": m["coverage"],
                "coverage_by_position": m["coverage_by_position"],
                "interval_width": m["interval_width"],
                "errors": m["errors"],
                "calibration": m.get("calibration_by_split") or m.get("calibration"),
                "coverage_by_condition": m.get("coverage_by_condition"),
            }
            oracle = float(np.quantile(np.where(np.isfinite(test_errors), test_errors, np.inf), 0.8))
            for scorer in SCORERS:
                width = m["interval_width"][scorer]["0.8"]["median_m"]
                lines.append(f"| {site} | {label} | {scorer} | {coverage_cells(m, scorer)} | {fmt(width)} | {fmt(oracle)} | {gate['n']} |")
    write_results("field_radii", {"machine": machine(), "runs": raw}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
