"""Where the bare solver's gross errors come from, per site, on the default simulation.

Usage: python experiments/error_tail.py [--n-events 1100]
For every simulated event: the default solver's 2-D error with the measured TDOAs, the error it would
make with the *true* TDOAs (so geometric ambiguity is separated from measurement failure), the
worst TDOA error in samples, the SNR and whether a trunk blocks a direct path. Writes
experiments/results/error_tail.md. Uses (and fills) the project cache under outputs/.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
from common import compose_cfg, machine, write_results

from acoustlab.core import columns as col
from acoustlab.core.contracts import SolverInputs
from acoustlab.method.pipeline import error_2d_m
from acoustlab.run.app import build_run, prepare_data
from acoustlab.stages.solver_columns import tdoa_matrix
from acoustlab.toolkit.event_physics import assumed_source_height_m
from acoustlab.toolkit.propagation import segment_trunk_clearance

log = logging.getLogger("experiments.error_tail")
GROSS_M = 5.0


def analyse(site_name: str, n_events: int) -> dict:
    cfg = compose_cfg([f"+site={site_name}", f"data.n_events={n_events}"])
    built = build_run(cfg)
    site, solver = built.site, built.components.solver
    data = prepare_data(cfg, built).dataset  # the data a real run gets: a fix outside the plausible region is a failure (inf)
    table, ev = data.features, data.events
    truth = ev[list(col.TRUE_XYZ)].to_numpy()
    err = error_2d_m(table[list(col.SOLVER_ESTIMATE_COLUMNS)].to_numpy(), truth)
    dist = np.sqrt(((truth[:, None, :] - site.mic_positions_m[None]) ** 2).sum(-1))
    c = ev[col.SPEED_OF_SOUND].to_numpy()
    true_tdoa = (dist - dist[:, :1]) / c[:, None]
    measured = tdoa_matrix(table, site.n_mics)
    tdoa_err_samples = np.abs(measured - true_tdoa).max(axis=1) * built.simulator.sample_rate_hz
    ideal = solver.solve(SolverInputs(site.mic_positions_m, true_tdoa, c, source_height_m=assumed_source_height_m(site)))
    ideal_err = error_2d_m(ideal.position_m, truth)
    occluded = np.zeros(len(ev), bool)
    if site.tree_positions_m.shape[0]:
        for k in range(site.n_mics):
            d, frac = segment_trunk_clearance(truth[:, :2], np.repeat(site.mic_positions_m[None, k, :2], len(ev), 0), site.tree_positions_m)
            occluded |= ((d < site.trunk_diameters_m[None] / 2) & (frac > 0) & (frac < 1)).any(axis=1)
    gross = err > GROSS_M
    bad_tdoa = tdoa_err_samples > 2.0
    height_off = np.abs(truth[:, 2] - np.mean(site.source_height_range_m))
    return {
        "n_events": int(len(ev)),
        "solver_error_m": {
            q: float(np.percentile(err, p, method="inverted_cdf")) for q, p in (("p50", 50), ("p90", 90), ("p95", 95), ("p99", 99))
        },
        "p95_over_p50": float(np.percentile(err, 95, method="inverted_cdf") / np.percentile(err, 50, method="inverted_cdf")),
        "gross_fraction": float(gross.mean()),
        "gross_with_bad_tdoa": float((gross & bad_tdoa).sum() / max(gross.sum(), 1)),
        "gross_with_true_tdoa_also_gross": float((gross & (ideal_err > GROSS_M)).sum() / max(gross.sum(), 1)),
        "bad_tdoa_fraction": float(bad_tdoa.mean()),
        "median_snr_db_gross": float(np.median(ev[col.SNR][gross])) if gross.any() else None,
        "median_snr_db_ok": float(np.median(ev[col.SNR][~gross])),
        "occluded_fraction_gross": float(occluded[gross].mean()) if gross.any() else None,
        "occluded_fraction_ok": float(occluded[~gross].mean()),
        "ideal_tdoa_error_m": {"p50": float(np.percentile(ideal_err, 50)), "p95": float(np.percentile(ideal_err, 95))},
        "median_source_height_offset_m": float(np.median(height_off)),
    }


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--n-events", type=int, default=1100)
    opts = parser.parse_args()
    result = {"machine": machine(), "n_events": opts.n_events, "sites": {s: analyse(s, opts.n_events) for s in ("frozen_lake", "forest")}}
    lines = [
        "# Where the bare solver's gross errors come from",
        "",
        f"`python experiments/error_tail.py --n-events {opts.n_events}` (default simulator, features and solver, all events; "
        "the data a run gets, from `prepare_data`: a fix outside the plausible region is a failure and counts as an infinite error; "
        "percentiles are empirical quantiles, no interpolation, so inf means the percentile falls among the failures)",
        "",
        "| | frozen_lake | forest |",
        "|---|---|---|",
    ]
    keys = [
        ("solver p50 (m)", lambda r: f"{r['solver_error_m']['p50']:.2f}"),
        ("solver p95 (m)", lambda r: f"{r['solver_error_m']['p95']:.1f}"),
        ("solver p99 (m)", lambda r: f"{r['solver_error_m']['p99']:.1f}"),
        ("p95 / p50", lambda r: f"{r['p95_over_p50']:.0f}"),
        (f"gross errors (> {GROSS_M:g} m)", lambda r: f"{100 * r['gross_fraction']:.1f} %"),
        ("… with a TDOA off by > 2 samples", lambda r: f"{100 * r['gross_with_bad_tdoa']:.0f} %"),
        ("… still gross with the true TDOAs (geometry)", lambda r: f"{100 * r['gross_with_true_tdoa_also_gross']:.0f} %"),
        ("median SNR, gross / fine (dB)", lambda r: f"{r['median_snr_db_gross']:.1f} / {r['median_snr_db_ok']:.1f}"),
        (
            "a trunk blocks a direct path, gross / fine",
            lambda r: f"{100 * (r['occluded_fraction_gross'] or 0):.0f} % / {100 * r['occluded_fraction_ok']:.0f} %",
        ),
        ("solver with true TDOAs, p50 / p95 (m)", lambda r: f"{r['ideal_tdoa_error_m']['p50']:.2f} / {r['ideal_tdoa_error_m']['p95']:.1f}"),
    ]
    for name, fmt in keys:
        lines.append(f"| {name} | {fmt(result['sites']['frozen_lake'])} | {fmt(result['sites']['forest'])} |")
    write_results("error_tail", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
