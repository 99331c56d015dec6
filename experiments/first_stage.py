"""The first stage (TDOA candidates → solver) side by side, on the same simulated events.

Usage: python experiments/first_stage.py [--n-events 1100] [--sites frozen_lake forest]

For every site, on the same cached simulation (default config), each variant is a GCC weighting
(``features.gcc.weighting``: PHAT, today's, or β-PHAT) and a solver option, and all solvers of one
weighting see the same ``SolverInputs``: today's default ``hyperbolic`` (top GCC peak of the pairs
with mic 0), ``robust`` (consensus over mic-0 candidates), the peer heuristic ``per_reference_mic``
(one fix per reference mic, lowest residual: OpenSoundscape's approach re-implemented from its
description) and ``consistent_set`` (jointly consistent candidates over all pairs, mics to trust).
The same plausibility bound applies to all (``pipeline.plausible_margin_fraction``); a fix it
rejects, or no fix at all, counts as a failure with an infinite error in every percentile.
Confidence intervals of the share > 5 m are 95 % bootstrap intervals over source positions.

Writes experiments/results/first_stage.md. Uses (and fills) the project cache under outputs/.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import replace

import numpy as np
from common import compose_cfg, machine, write_results

from acoustlab.core.contracts import SolverInputs
from acoustlab.method.pipeline import error_2d_m
from acoustlab.reporting.metrics import error_summary
from acoustlab.run.registry import build, build_feature_sets, to_plain
from acoustlab.stages.cache import StageCache
from acoustlab.stages.dataset import SimulationPlan, load_or_build_simulated
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import bound_fixes, solver_inputs_for

log = logging.getLogger("experiments.first_stage")
#: (label, GCC weighting, solver option, solver overrides): the previous default first, the peer heuristic on the same inputs.
VARIANTS = (
    ("hyperbolic, PHAT (before)", "phat", "hyperbolic", ()),
    ("robust, PHAT", "phat", "baseline_robust", ()),
    ("per_reference_mic (peer), PHAT", "phat", "baseline_per_reference_mic", ()),
    ("consistent_set, PHAT", "phat", "consistent_set", ()),
    ("per_reference_mic (peer), β-PHAT", "beta_phat", "baseline_per_reference_mic", ()),
    ("consistent_set, β-PHAT, 2-D", "beta_phat", "consistent_set", ("solver.dimensions=2",)),
    ("consistent_set, β-PHAT (default: 3-D with ≥ 4 mics)", "beta_phat", "consistent_set", ()),
)
GROSS_M = 5.0


def share_ci(gross: np.ndarray, groups: np.ndarray, n_boot: int = 1000, seed: int = 0) -> tuple[float, float]:
    """95 % bootstrap interval of the share of gross errors, resampling source positions."""
    rng = np.random.default_rng(seed)
    ids, inverse = np.unique(groups, return_inverse=True)
    per_group = np.bincount(inverse, weights=gross.astype(float)), np.bincount(inverse)
    draws = rng.integers(0, ids.size, size=(n_boot, ids.size))
    shares = per_group[0][draws].sum(1) / per_group[1][draws].sum(1)
    return float(np.percentile(shares, 2.5)), float(np.percentile(shares, 97.5))


def load(site_name: str, n_events: int, weighting: str, extra: tuple[str, ...] = (), with_data: bool = False):
    """Site, solver inputs, truth and position ids of the cached default simulation with these GCC weights
    (``extra``: more overrides; ``with_data``: the dataset as a sixth item)."""
    cfg = compose_cfg([f"+site={site_name}", f"data.n_events={n_events}", f"features.gcc.weighting={weighting}", *extra])
    site = site_from_config(cfg.site)
    features = build_feature_sets(cfg.features)
    plan = SimulationPlan(seed=cfg.seed, **{**to_plain(cfg.data), "n_events": n_events})
    data = load_or_build_simulated(
        site,
        build(cfg.simulator, "simulator"),
        to_plain(cfg.simulator),
        features,
        to_plain(cfg.features.groups),
        plan,
        StageCache(cfg.cache.dir),
    )
    truth = data.events[["x_m", "y_m", "z_m"]].to_numpy(float)
    out = (site, solver_inputs_for(data.features, data.events, site), truth, data.events["position_id"].to_numpy(), cfg)
    return (*out, data) if with_data else out


#: The per-event fields of ``SolverInputs`` (the mics and the source height are shared by all events).
PER_EVENT = ("tdoa_s", "speed_of_sound_m_s", "received_level_db", "pair_lag_candidates_s", "pair_lag_weights")


def first_rows(inputs: SolverInputs, n: int) -> SolverInputs:
    """The first ``n`` events of a batch of solver inputs (for warming up)."""
    head = {name: getattr(inputs, name) for name in PER_EVENT}
    return replace(inputs, **{name: v if v is None or np.ndim(v) == 0 else np.asarray(v)[:n] for name, v in head.items()})


def evaluate(site_name: str, n_events: int) -> dict:
    out: dict = {}
    loaded = {}
    for label, weighting, solver_name, solver_overrides in VARIANTS:
        if weighting not in loaded:
            loaded[weighting] = load(site_name, n_events, weighting)
        site, inputs, truth, groups, cfg = loaded[weighting]
        out.update(n_events=len(truth), n_positions=int(np.unique(groups).size))
        solver = build(compose_cfg([f"+site={site_name}", f"solver={solver_name}", *solver_overrides]).solver, "solver")
        solver.solve(first_rows(inputs, 8))  # warm-up
        start = time.perf_counter()
        result = solver.solve(inputs)
        elapsed = time.perf_counter() - start
        position, failure = bound_fixes(result.position_m, site, float(cfg.pipeline.plausible_margin_fraction))
        err = error_2d_m(position, truth)
        gross = ~(err <= GROSS_M)
        summary = error_summary(err)
        out[label] = {
            **summary,
            "solver": solver_name,
            "weighting": weighting,
            "share_gross": float(gross.mean()),
            "share_gross_ci95": share_ci(gross, groups),
            "share_no_fix": float((failure > 0).mean()),
            "ms_per_event": 1000 * elapsed / len(err),
        }
        log.info(
            "%s %s: p50 %.2f p95 %.1f, > 5 m %.1f %%, no fix %.1f %%, %.2f ms/event",
            site_name,
            label,
            summary["p50"],
            summary["p95"],
            100 * gross.mean(),
            100 * (failure > 0).mean(),
            out[label]["ms_per_event"],
        )
    return out


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-events", type=int, default=1100)
    parser.add_argument("--sites", nargs="+", default=["frozen_lake", "forest"])
    opts = parser.parse_args()
    sites = {s: evaluate(s, opts.n_events) for s in opts.sites}
    lines = [
        "# The first stage side by side (same events, same inputs)",
        "",
        f"`python experiments/first_stage.py --n-events {opts.n_events}`: default simulation and features; failures "
        "(no fix, or a fix outside the plausible region) count as infinite errors in every percentile.",
        "",
    ]
    fmt = lambda v: "∞" if not np.isfinite(v) else f"{v:.2f}" if v < 10 else f"{v:.0f}"  # noqa: E731
    for site_name, res in sites.items():
        lines += [
            f"## {site_name}: {res['n_events']} events at {res['n_positions']} source positions",
            "",
            "| solver | p50 (m) | p90 | p95 | p99 | > 5 m (95 % CI by position) | no fix | ms / event |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for name, *_ in VARIANTS:
            r = res[name]
            lo, hi = r["share_gross_ci95"]
            lines.append(
                f"| {name} | {fmt(r['p50'])} | {fmt(r['p90'])} | {fmt(r['p95'])} | {fmt(r['p99'])} | "
                f"{100 * r['share_gross']:.1f} % ({100 * lo:.1f}–{100 * hi:.1f}) | {100 * r['share_no_fix']:.1f} % | {r['ms_per_event']:.2f} |"
            )
        lines.append("")
    write_results("first_stage", {"machine": machine(), "n_events": opts.n_events, "sites": sites}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
