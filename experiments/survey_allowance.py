"""Does the radii's survey allowance hold what a GPS survey's error does to the fixes, over surveys and for one array?

Usage: python experiments/survey_allowance.py [--sites frozen_lake forest] [--sigma 2.0] [--arrays 100] [--positions 150]

For each site, ``--arrays`` simulated surveys: every mic stands off its stated position by
N(0, ``--sigma``) per axis; ``--positions`` sources drawn uniformly over the mics' box grown by a
quarter of the array's extent on each side. Each source's fix is solved (Gauss–Newton, exact
arrival times of the true array) with the stated positions, as a user with GPS-placed mics does;
its shift from the truth is what the survey error does to it. The allowance is computed as a run
computes it, at the shifted fix with the stated mics and ``conformal.input_uncertainty.
mic_position_m = --sigma`` (``acoustlab.toolkit.input_uncertainty.allowance_m``), and compared with
the shift in two forms side by side: the radius that follows the shift (the ℓ-quantile of its
Monte Carlo, or of the first-order Gaussian with its two axes) and a round radius of the same σ
(σ · √(−2 ln(1 − ℓ)), the form before). Reported at 0.5, 0.8 and 0.95: the share of shifts held,
averaged over arrays (what the allowance promises: marginal over surveys of the stated size),
and its 10 % quantile over arrays (what one array, the user's, has with probability 0.9).

Only the survey's effect is measured: exact arrival times, no acoustics, no conformal part. The
whole-pipeline figure on the second simulator is in docs/localize.md. Writes
experiments/results/survey_allowance.md.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
from common import compose_cfg, machine, write_results

from acoustlab.stages.sites import site_from_config
from acoustlab.toolkit.input_uncertainty import InputUncertainty, allowance_m, fix_shift_m, level_factor

log = logging.getLogger("experiments.survey_allowance")
LEVELS = (0.5, 0.8, 0.95)


def one_site(site_name: str, sigma_m: float, n_arrays: int, n_positions: int, seed: int) -> dict:
    """Per-array shares of shifts held by each form of the allowance, and the median radii."""
    site = site_from_config(compose_cfg([f"+site={site_name}"]).site)
    stated = site.mic_positions_m
    low, high = stated[:, :2].min(axis=0), stated[:, :2].max(axis=0)
    grow = 0.25 * (high - low)
    rng = np.random.default_rng([seed, n_arrays, n_positions])
    allowance_stated = InputUncertainty(temperature_c=0.0, mic_position_m=sigma_m)
    held = {form: np.zeros((n_arrays, len(LEVELS))) for form in ("follows the shift", "round, same σ", "mics taken as exact")}
    radii = {form: [] for form in held}
    weather = (np.full(n_positions, 10.0), np.full(n_positions, 60.0))
    for a in range(n_arrays):
        true = stated.copy()
        true[:, :2] += rng.normal(0.0, sigma_m, (site.n_mics, 2))
        source = np.column_stack([rng.uniform(low - grow, high + grow, (n_positions, 2)), np.full(n_positions, 1.5)])
        shift = fix_shift_m(true, source, *weather, np.zeros(1), np.zeros((1, site.n_mics)), (stated - true)[None, :, :2], 20)[:, 0]
        fixed = np.isfinite(shift).all(axis=1)
        estimate = source[fixed].copy()
        estimate[:, :2] += shift[fixed]
        found = allowance_m(stated, estimate, weather[0][fixed], weather[1][fixed], allowance_stated, LEVELS)
        distance = np.sqrt((shift[fixed] ** 2).sum(axis=1))
        forms = {
            "follows the shift": found.radius_m,
            "round, same σ": found.sigma_m[:, None] * np.array([level_factor(level) for level in LEVELS])[None],
            "mics taken as exact": np.zeros_like(found.radius_m),
        }
        for form, radius in forms.items():
            held[form][a] = (distance[:, None] <= radius).mean(axis=0)
            radii[form].append(radius)
    return {
        form: {
            str(level): {
                "mean over arrays": float(held[form][:, k].mean()),
                "10 % of arrays below": float(np.quantile(held[form][:, k], 0.1)),
                "median radius m": float(np.median(np.concatenate(radii[form])[:, k])),
            }
            for k, level in enumerate(LEVELS)
        }
        for form in held
    } | {"n_mics": site.n_mics}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sites", nargs="+", default=["frozen_lake", "forest"])
    parser.add_argument("--sigma", type=float, default=2.0, help="survey error per axis, m")
    parser.add_argument("--arrays", type=int, default=100)
    parser.add_argument("--positions", type=int, default=150)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    results = {site: one_site(site, args.sigma, args.arrays, args.positions, args.seed) for site in args.sites}
    rows = ["| site | radius | " + " | ".join(f"{level}: mean / 10 % of arrays below / median radius (m)" for level in LEVELS) + " |"]
    rows.append("|---|---|" + "---|" * len(LEVELS))
    for site, result in results.items():
        for form in ("follows the shift", "round, same σ", "mics taken as exact"):
            cells = [
                f"{c['mean over arrays']:.3f} / {c['10 % of arrays below']:.3f} / {c['median radius m']:.2f}"
                for c in (result[form][str(level)] for level in LEVELS)
            ]
            rows.append(f"| {site} ({result['n_mics']} mics) | {form} | " + " | ".join(cells) + " |")
    markdown = [
        "# The survey allowance against what a GPS survey's error does to the fixes",
        "",
        f"`python experiments/survey_allowance.py --sites {' '.join(args.sites)} --sigma {args.sigma:g} --arrays {args.arrays} "
        f"--positions {args.positions}`: {args.arrays} simulated surveys per site (mics N(0, {args.sigma:g} m) per axis off their "
        f"stated positions), {args.positions} sources each over the mics' box grown by a quarter of its extent; the share of "
        "fixes whose shift (solved with the stated positions from exact arrival times) lies within the allowance's radius, "
        "averaged over arrays and its 10 % quantile over arrays, with the median radius.",
        "",
        *rows,
        "",
        "The allowance is marginal over surveys of the stated size: the mean over arrays is what it promises; one array's "
        "coverage over positions scatters around it, because its mics' errors shift every fix the same way. Only the survey's "
        f"effect is measured here (exact arrival times). Machine: {machine()}.",
    ]
    write_results("survey_allowance", {"sites": results, "sigma_m": args.sigma, "arrays": args.arrays}, markdown)


if __name__ == "__main__":
    main()
