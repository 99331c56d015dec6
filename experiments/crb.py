"""Median solver error ÷ Cramér–Rao bound per site: where the bound's assumptions hold, and outdoors.

Usage: python experiments/crb.py [--n-events 1100]

For each site, the default first stage (β-PHAT GCC candidates, consistent-set solver) on

* ``free_field`` with white noise only (``site.noise.regimes=[{kind: white}]``): direct path,
  no reflections, no impairments, the conditions the bound assumes;
* the default ``outdoor`` simulator (ground reflection, trunks, air absorption, real noise).

* ``free_field`` as above with the 3-D solver (``solver.dimensions=3``, sites with ≥ 4 mics): the
  2-D solver assumes the middle of the site's source-height range, so on a site whose sources
  spread in height that assumption, not the TDOAs, limits it.

The bound per event is GDOP × c × σ_τ at the true position with the two-sensor TDOA bound from
the event's measured SNR, RMS bandwidth, duration and band (``crb_m`` in metrics.json). Reported:
median error ÷ median bound, the median of the per-event ratio, and the share of events whose
error is within 3× their bound; gross errors (> 5 m) are excluded from the ratios and counted
separately, since the bound describes the small-error regime. Writes
experiments/results/crb.md.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
from common import compose_cfg, machine, write_results
from first_stage import load

from acoustlab.method.pipeline import crb_from_features, error_2d_m
from acoustlab.reporting.metrics import GROSS_ERROR_M, share_gross
from acoustlab.run.registry import build
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import bound_fixes

log = logging.getLogger("experiments.crb")
#: (data overrides, solver overrides) per condition
CONDITIONS = {
    "free field, white noise, 2-D solver": (("simulator=free_field", "site.noise.regimes=[{kind: white}]"), ("solver.dimensions=2",)),
    "free field, white noise, 3-D solver": (("simulator=free_field", "site.noise.regimes=[{kind: white}]"), ("solver.dimensions=3",)),
    "outdoor, 2-D solver": ((), ("solver.dimensions=2",)),
    "outdoor, 3-D solver (default with ≥ 4 mics)": ((), ("solver.dimensions=3",)),
}


def evaluate(site_name: str, n_events: int, overrides: tuple[str, ...], solver_overrides: tuple[str, ...] = ()) -> dict:
    site, inputs, truth, _, cfg, data = load(site_name, n_events, "beta_phat", overrides, with_data=True)
    solver = build(compose_cfg([f"+site={site_name}", "solver=consistent_set", *solver_overrides]).solver, "solver")
    position, _ = bound_fixes(solver.solve(inputs).position_m, site, float(cfg.pipeline.plausible_margin_fraction))
    err = error_2d_m(position, truth)
    crb = crb_from_features(data.features, data.events, site)
    fine = (err <= GROSS_ERROR_M) & np.isfinite(crb) & (crb > 0)
    ratio = err[fine] / crb[fine]
    return {
        "n_events": int(err.size),
        "share_gross": share_gross(err),
        "median_error_m": float(np.median(err[fine])),
        "median_crb_m": float(np.median(crb[fine])),
        "median_error_over_median_crb": float(np.median(err[fine]) / np.median(crb[fine])),
        "median_ratio": float(np.median(ratio)),
        "share_within_3x": float(np.mean(ratio <= 3.0)),
    }


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-events", type=int, default=1100)
    parser.add_argument("--sites", nargs="+", default=["frozen_lake", "forest"])
    opts = parser.parse_args()
    results = {
        s: {
            name: evaluate(s, opts.n_events, data_ov, solver_ov)
            for name, (data_ov, solver_ov) in CONDITIONS.items()
            if site_from_config(compose_cfg([f"+site={s}"]).site).n_mics >= 4 or "solver.dimensions=3" not in solver_ov
        }
        for s in opts.sites
    }
    lines = [
        "# Solver error against the Cramér–Rao bound",
        "",
        f"`python experiments/crb.py --n-events {opts.n_events}`: consistent-set solver on β-PHAT candidates; "
        "ratios over events with error ≤ 5 m (gross errors counted separately).",
        "",
        "| site | simulation | median error (m) | median CRB (m) | median error ÷ median CRB | median of error ÷ CRB | within 3× CRB | > 5 m |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s, by in results.items():
        for name, r in by.items():
            lines.append(
                f"| {s} | {name} | {r['median_error_m']:.3g} | {r['median_crb_m']:.3g} | {r['median_error_over_median_crb']:.1f} | "
                f"{r['median_ratio']:.1f} | {100 * r['share_within_3x']:.0f} % | {100 * r['share_gross']:.1f} % |"
            )
    write_results("crb", {"machine": machine(), "n_events": opts.n_events, "sites": results}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
