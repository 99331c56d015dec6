"""What coverage does one set of K playback spots give? The radii's calibration step over thousands of spot sets.

Usage: python experiments/field_radii_draws.py [--sites frozen_lake forest] [--spots 5 10 20] [--draws 2000] [--n-positions 60]

``field_radii.py`` runs the whole method for three draws of the spots; one draw's coverage scatters
so widely that three cannot tell whether the mean is within ±0.05 of the level. This holds the
method fixed and redraws only the spots. Per site, the method of ``field_radii.py`` (XGBoost point
model, XGBoost-quantile error model, learned gate) is trained on 1,000 events of acoustlab's
simulation and run on ``--n-positions`` × 5 calls rendered by the second simulator (pyroomacoustics).
Then, ``--draws`` times, K positions drawn at random are the playback spots: the scorer
(``SplitConformal``, ``fixed`` and ``gdop_scaled`` as configured in ``conf/conformal/paper.yaml``,
position-level) is fitted on their calls and its radii cover the other positions' calls or not.
Position methods side by side: ``pooled`` (every playback, the default) and ``subsample`` (one
playback per spot). Reported per level: the mean coverage over draws (what the guarantee is
about), the 5–95 % range of one set's coverage (what one user may get), and the median radius at
0.8 over the oracle's (the 0.8-quantile of the test errors of that draw). In ``field_radii.py`` the
spots also join the point model's training; here they do not, which isolates the calibration.
Writes experiments/results/field_radii_draws.md.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
import pandas as pd
from common import REPO, machine, run_in_process, write_results

from plugins.conformal.split import SplitConformal

log = logging.getLogger("experiments.field_radii_draws")
METHOD = ["model=xgboost", "error_model=xgboost_quantile", "gate=learned", "conformal=paper"]
LEVELS = [0.5, 0.8, 0.95]
SCORERS = {"fixed": {"normaliser": "none"}, "gdop_scaled": {"normaliser": "gdop"}}
POSITION_METHODS = ("pooled", "subsample")
#: the run's predictions (git-ignored)
KEPT = REPO / "outputs" / "bench_field_radii_draws"
#: a failed fix's error, m: larger than any radius, finite so the quantiles can order it
FAILED_M = 1e9


def draw_coverage(predictions: pd.DataFrame, n_spots: int, scorer: dict, method: str, draws: int, seed: int) -> dict[str, np.ndarray]:
    """Per draw of ``n_spots`` spots: position-level coverage of the other positions at each level, and the 0.8 radius / oracle."""
    error = np.nan_to_num(predictions["error_gate_m"].to_numpy(float), nan=FAILED_M, posinf=FAILED_M)
    predicted = predictions["predicted_error_m"].to_numpy(float)
    gdop = predictions["gdop"].to_numpy(float)
    position = predictions["position_id"].to_numpy()
    ids = np.unique(position)
    rng = np.random.default_rng(seed)
    coverage, ratio = [], []
    for _ in range(draws):
        spot = np.isin(position, rng.choice(ids, n_spots, replace=False))
        fitted = SplitConformal(**scorer, calibration_unit="position", position_method=method, seed=int(rng.integers(2**31))).fit(
            error[spot], predicted[spot], gdop[spot], LEVELS, groups=position[spot]
        )
        radius = fitted.radius(predicted[~spot], gdop[~spot])  # (T, L)
        covered = pd.DataFrame(error[~spot, None] <= radius).groupby(position[~spot]).mean()  # per test position
        coverage.append(covered.mean(axis=0).to_numpy())
        ratio.append(np.median(radius[:, 1]) / np.quantile(error[~spot], 0.8))
    return {"coverage": np.asarray(coverage), "radius_over_oracle": np.asarray(ratio)}


def cells(result: dict[str, np.ndarray]) -> str:
    out = []
    for k, _ in enumerate(LEVELS):
        c = result["coverage"][:, k]
        finite = np.isfinite(c)
        out.append(
            f"{c[finite].mean():.3f} ({np.quantile(c[finite], 0.05):.2f}–{np.quantile(c[finite], 0.95):.2f})" if finite.any() else "—"
        )
    return " | ".join(out)


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["frozen_lake", "forest"])
    parser.add_argument("--spots", nargs="+", type=int, default=[5, 10, 20])
    parser.add_argument("--draws", type=int, default=2000)
    parser.add_argument("--n-positions", type=int, default=60)
    opts = parser.parse_args()
    lines = [
        "# Radii calibrated on K playback spots: the coverage of one set, over many draws of the spots",
        "",
        f"`python experiments/field_radii_draws.py --sites {' '.join(opts.sites)} --spots {' '.join(map(str, opts.spots))} "
        f"--draws {opts.draws} --n-positions {opts.n_positions}`. Second simulator, {opts.n_positions} positions × 5 calls per site; "
        f"the method fixed (trained on acoustlab's simulation), {opts.draws} draws of the K spots; position-level coverage of the "
        "other positions' calls. Each cell: mean over draws (5–95 % range of one draw). A level the spots cannot guarantee "
        "(19 spots for 0.95 pooled) has infinite radii (coverage 1).",
        "",
        "| site | K spots | scorer | position method | 0.50 | 0.80 | 0.95 | median 0.80 radius ÷ oracle |",
        "|---|---|---|---|---|---|---|---|",
    ]
    raw: dict[str, dict] = {}
    for site in opts.sites:
        kept = KEPT / f"{site}.parquet"
        run_in_process(
            [f"+site={site}", *METHOD, "protocol=field_eval", "field=image_source", f"field.n_positions={opts.n_positions}"], kept
        )
        predictions = pd.read_parquet(kept)
        for n_spots in opts.spots:
            for name, scorer in SCORERS.items():
                for method in POSITION_METHODS:
                    result = draw_coverage(predictions, n_spots, scorer, method, opts.draws, seed=n_spots)
                    raw[f"{site}/{n_spots}/{name}/{method}"] = {
                        "mean_coverage": result["coverage"].mean(axis=0).tolist(),
                        "coverage_5_95": np.quantile(result["coverage"], [0.05, 0.95], axis=0).tolist(),
                        "median_radius_over_oracle": float(np.median(result["radius_over_oracle"])),
                    }
                    lines.append(
                        f"| {site} | {n_spots} | {name} | {method} | {cells(result)} | {np.median(result['radius_over_oracle']):.2f} |"
                    )
    write_results("field_radii_draws", {"machine": machine(), "results": raw}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
