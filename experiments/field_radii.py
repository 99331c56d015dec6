"""Do radii hold at a site after calibrating them on a few playback spots? Second simulator, held out by position.

Usage: python experiments/field_radii.py [--sites frozen_lake forest] [--spots 10 20] [--n-positions 60] [--draws 3]

Per site: the method (XGBoost point model, XGBoost-quantile error model, learned gate, the paper's
fixed and GDOP-scaled conformal) trained on 1,000 events of acoustlab's simulator, evaluated on
recordings rendered by pyroomacoustics (``field=image_source``, ``--n-positions`` × 5 events, 30 %
of the positions outside the simulated region):

* **without calibration**: radii calibrated on the simulation (``protocol=field_eval``);
* **with K spots**: K of the field positions drawn at random are playback spots
  (``protocol.calibration_positions=K``): they join training and calibrate the radii at the
  position level; the other positions are the test. ``--draws`` draws of the spots
  (``protocol.seed``): a user has one, and the spread over draws is what one set may give. A level
  the spots cannot guarantee gets a radius rescaled from the simulation's
  (``conformal.unsupported_levels=rescaled``), marked "n.g." (not guaranteed).

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
METHOD = [
    "model=xgboost",
    "error_model=xgboost_quantile",
    "gate=learned",
    "conformal=mondrian_region",
    "conformal.unsupported_levels=rescaled",
]
LEVELS = ("0.5", "0.8", "0.95")
SCORERS = ("fixed", "gdop_scaled", "gdop_by_region")
#: the runs' predictions (git-ignored)
KEPT = REPO / "outputs" / "bench_field_radii"


def coverage_cells(runs: list[dict], scorer: str) -> str:
    """Per level: coverage per detection / per position, the mean over draws with the range of per-detection coverage."""
    cells = []
    for lv in LEVELS:
        detection = np.array([m["coverage"][scorer][lv] for m in runs], dtype=float)
        position = np.array([m["coverage_by_position"][scorer][lv]["mean"] for m in runs], dtype=float)
        not_guaranteed = any(lv in c.get("not_guaranteed_levels", []) for m in runs for c in m.get("calibration_by_split") or [])
        if np.isnan(detection).all():
            cells.append("—")
            continue
        spread = f" ({detection.min():.2f}–{detection.max():.2f})" if len(runs) > 1 else ""
        cells.append(f"{detection.mean():.2f} / {position.mean():.2f}{spread}{' n.g.' if not_guaranteed else ''}")
    return " | ".join(cells)


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["frozen_lake", "forest"])
    parser.add_argument("--spots", nargs="+", type=int, default=[10, 20])
    parser.add_argument("--n-positions", type=int, default=60)
    parser.add_argument("--draws", type=int, default=3)
    opts = parser.parse_args()
    lines = [
        "# Radii at a site, calibrated on playback spots (second simulator, held out by position)",
        "",
        f"`python experiments/field_radii.py --sites {' '.join(opts.sites)} --spots {' '.join(map(str, opts.spots))} "
        f"--n-positions {opts.n_positions} --draws {opts.draws}`. Coverage per detection / per position (mean over test positions) "
        f"at 0.50, 0.80 and 0.95, averaged over {opts.draws} draws of the spots with the range of per-detection coverage over draws "
        "in brackets; 'n.g.': a level the spots cannot guarantee, its radius rescaled from the simulation's. Oracle: the "
        "level-quantile of the test errors.",
        "",
        "| site | radii calibrated on | scorer | 0.50 | 0.80 | 0.95 | median 0.80 radius (m) | oracle 0.80 (m) | test events |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    raw: dict[str, dict] = {}
    for site in opts.sites:
        base = [f"+site={site}", *METHOD, "protocol=field_eval", "field=image_source", f"field.n_positions={opts.n_positions}"]
        for spots in [0, *opts.spots]:
            label = "the simulation" if spots == 0 else f"{spots} field spots"
            runs, oracles = [], []
            for draw in range(1 if spots == 0 else opts.draws):
                kept = KEPT / f"{site}_{spots}_{draw}.parquet"
                m = run_in_process([*base, f"protocol.calibration_positions={spots}", f"protocol.seed={draw}"], kept)
                test_errors = pd.read_parquet(kept)["error_gate_m"].to_numpy(float)
                oracles.append(float(np.quantile(np.where(np.isfinite(test_errors), test_errors, np.inf), 0.8)))
                runs.append(m)
                raw[f"{site}/{spots}/{draw}"] = {
                    "coverage": m["coverage"],
                    "coverage_by_position": m["coverage_by_position"],
                    "interval_width": m["interval_width"],
                    "errors": m["errors"],
                    "calibration": m.get("calibration_by_split") or m.get("calibration"),
                    "coverage_by_condition": m.get("coverage_by_condition"),
                }
            for scorer in SCORERS:
                width = float(np.mean([m["interval_width"][scorer]["0.8"]["median_m"] for m in runs]))
                n = int(np.mean([m["errors"]["gate"]["n"] for m in runs]))
                lines.append(
                    f"| {site} | {label} | {scorer} | {coverage_cells(runs, scorer)} | {fmt(width)} | {fmt(float(np.mean(oracles)))} | {n} |"
                )
    write_results("field_radii", {"machine": machine(), "runs": raw}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
