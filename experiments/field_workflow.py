"""The field workflow end to end on the second simulator: an impaired array calibrated from a sweep, radii from calls at 10 spots.

Usage: python experiments/field_workflow.py [--sites frozen_lake forest] [--arrays 2] [--n-positions 100] [--spots 10] [--draws 2000]

Per site and array draw (``field.array_seed``), recordings rendered by pyroomacoustics
(``field=image_source``) with the errors a field study has (``field_calibration.IMPAIRED``: mics
N(0, 2 m) per axis off their stated positions, clocks within ±1 ms, the thermometer 3 °C high). The
method is the one of ``field_radii.py`` (XGBoost point model, XGBoost-quantile error model, learned
gate, the paper's fixed and GDOP-scaled radii), trained on acoustlab's own simulation; the field's
``--n-positions`` × 5 calls (30 % of the positions outside the array) are the test. Three arms,
each a ``protocol=field_eval`` run of the same method:

* **calibrated**: ``calibrate`` from the 1–8 kHz sweep played 3 times at ``--spots`` spots that
  ``plan_playbacks`` puts (``calibration=PATH``), then calls at ``--spots`` of the field's positions
  calibrate the radii at the position level. The spots are redrawn ``--draws`` times from the
  run's predictions (the scorers of ``conf/conformal/paper.yaml``, each position's calls pooled as
  by default, and one call drawn per position, ``position_method=subsample``, from the same
  predictions); each draw's coverage is the mean over the other positions of the share of their calls
  covered. The spots of calls are not the sweep's, so no call is solved with an array fitted on
  its own spot. Also one run with ``protocol.calibration_positions`` (the spots join training and the
  pipeline calibrates the radii itself): one user's set of spots, through the job's own code path.
* **without playbacks**: the stated (impaired) array as it is; the radii are the simulation's grown by
  the input allowance for what the user states of the instruments (mics 2 m per axis, clocks
  0.58 ms, the standard deviation of a uniform ±1 ms, thermometer 3 °C).
* **surveyed**: the same sources with no errors (mics, clocks, thermometer exact), no allowance: the
  radius a surveyed array gets.

Reported per arm: the share of calls whose reported position is > 5 m off against the solver's
(failures as errors; 95 % position-bootstrap intervals), position-level coverage at 0.5 / 0.8 / 0.95,
the median radius and the oracle radius (the level-quantile of the test errors). Writes
experiments/results/field_workflow.md.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
from common import REPO, machine, run_in_process, write_results
from field_calibration import IMPAIRED, calibrate
from field_radii_draws import FAILED_M, LEVELS, POSITION_METHODS, SCORERS, draw_coverage

from acoustlab.core import columns as col
from acoustlab.reporting.metrics import coverage_by_position, position_bootstrap_ci, share_gross

log = logging.getLogger("experiments.field_workflow")
METHOD = ["model=xgboost", "error_model=xgboost_quantile", "gate=learned", "conformal=paper"]
#: what a user without playbacks states of the instruments: a consumer GPS, a clock within ±1 ms (uniform), a thermometer
STATED_INPUTS = [
    "conformal.input_uncertainty.mic_position_m=2.0",
    "conformal.input_uncertainty.clock_offset_s=0.00058",
    "conformal.input_uncertainty.temperature_c=3.0",
]
#: exact instruments: no allowance
EXACT_INPUTS = ["conformal.input_uncertainty.temperature_c=0.0"]
#: the runs' predictions (git-ignored)
KEPT = REPO / "outputs" / "bench_field_workflow"
N_BOOT = 1000


def errors_of(predictions: pd.DataFrame, column: str) -> np.ndarray:
    """A column of 2-D errors, m, failures (NaN or infinite) as ``FAILED_M``."""
    return np.nan_to_num(predictions[column].to_numpy(float), nan=FAILED_M, posinf=FAILED_M)


def gross_share(predictions: pd.DataFrame, method: str) -> dict[str, float]:
    """A method's share of calls > 5 m off (failures included) with its 95 % position-bootstrap interval (the project's own)."""
    low, high = position_bootstrap_ci(predictions, [], [], n_boot=N_BOOT)[col.METRICS_ERRORS][method]["share_gt_5m"]
    return {"share": share_gross(predictions[col.error_m(method)].to_numpy(float)), "low": low, "high": high}


def position_coverage(predictions: pd.DataFrame, scorer: str) -> dict[str, float]:
    """Per level: the mean over positions of the share of their calls within the run's own radius; NaN where it has none."""
    by_position = coverage_by_position(predictions, list(LEVELS), [scorer])[scorer]
    return {
        str(level): by_position[col.level_key(level)]["mean"] if np.isfinite(predictions[col.radius(scorer, level)]).any() else float("nan")
        for level in LEVELS
    }


def radius_summary(predictions: pd.DataFrame, scorer: str) -> dict[str, float]:
    """Per level: the median radius and the oracle radius (the level-quantile of the calls' errors), m."""
    error = errors_of(predictions, "error_gate_m")
    return {
        str(level): {
            "median_m": float(np.median(predictions[f"radius__{scorer}__{level}"].to_numpy(float))),
            "oracle_m": float(np.quantile(error, level)),
        }
        for level in LEVELS
    }


def arm(overrides: list[str], kept: Path) -> tuple[pd.DataFrame, dict]:
    """One field_eval run: its predictions (the field's positions) and metrics."""
    metrics = run_in_process(overrides, kept)
    return pd.read_parquet(kept), metrics


def array_runs(site: str, a: int, opts: argparse.Namespace) -> dict[str, dict]:
    """The three arms (and the job's own calibrated run) for array ``a`` of ``site``."""
    seed = 100 + a
    field = [
        f"+site={site}",
        *METHOD,
        "protocol=field_eval",
        "field=image_source",
        f"field.n_positions={opts.n_positions}",
        "field.events_per_position=5",
        f"field.array_seed={seed}",
        f"field.seed={2000 + a}",
    ]
    out: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        body = calibrate(site, seed, opts.spots, "planned", Path(tmp) / "cal", "image_source", signal="sweep")
        path = Path(tmp) / "cal" / "calibration.json"
        calibrated = [*field, *IMPAIRED, f"calibration={path}"]
        predictions, _ = arm(calibrated, KEPT / f"{site}_{a}_calibrated.parquet")
        draws = {
            method: {name: draw_coverage(predictions, opts.spots, scorer, method, opts.draws, seed=a) for name, scorer in SCORERS.items()}
            for method in POSITION_METHODS
        }
        own, metrics = arm([*calibrated, f"protocol.calibration_positions={opts.spots}"], KEPT / f"{site}_{a}_one_set.parquet")
        out["calibrated"] = {
            "predictions": predictions,
            "draws": draws,
            "temperature_offset_c": body["temperature_offset_c"],
            "one_set": {"predictions": own, "one_set": [c.get("one_set") for c in metrics.get("calibration_by_split", [])]},
        }
        out["without playbacks"] = {"predictions": arm([*field, *IMPAIRED, *STATED_INPUTS], KEPT / f"{site}_{a}_unsurveyed.parquet")[0]}
        out["surveyed"] = {"predictions": arm([*field, *EXACT_INPUTS], KEPT / f"{site}_{a}_surveyed.parquet")[0]}
    return out


def pooled_predictions(runs: list[dict], name: str) -> pd.DataFrame:
    """One arm's predictions over arrays, position ids made distinct per array."""
    frames = []
    for a, r in enumerate(runs):
        p = r[name]["predictions"].copy()
        p["position_id"] = p["position_id"].astype(np.int64) + 10**6 * a
        frames.append(p)
    return pd.concat(frames, ignore_index=True)


def site_rows(site: str, runs: list[dict], opts: argparse.Namespace) -> tuple[list[str], dict]:
    """The site's table rows and raw figures."""
    rows, raw = [], {}
    for name, method in (*(("calibrated", m) for m in POSITION_METHODS), ("without playbacks", None), ("surveyed", None)):
        p = pooled_predictions(runs, name)
        solver, reported = gross_share(p, "solver"), gross_share(p, "gate")
        label = name if method in (None, "pooled") else f"{name}, {method}"
        raw[label] = {"n_calls": len(p), "solver_gt_5m": solver, "reported_gt_5m": reported}
        for scorer in SCORERS:
            if name == "calibrated":
                coverage = np.concatenate([r[name]["draws"][method][scorer]["coverage"] for r in runs])
                ratio = np.concatenate([r[name]["draws"][method][scorer]["radius_over_oracle"] for r in runs])
                cells = [
                    f"{coverage[:, k].mean():.3f} ({np.quantile(coverage[:, k], 0.05):.2f}–{np.quantile(coverage[:, k], 0.95):.2f})"
                    for k in range(len(LEVELS))
                ]
                raw[label][scorer] = {
                    "mean_coverage_over_draws": coverage.mean(axis=0).tolist(),
                    "coverage_5_95": np.quantile(coverage, [0.05, 0.95], axis=0).tolist(),
                    "median_radius_over_oracle_0.8": float(np.median(ratio)),
                }
                radius = f"{np.median(ratio):.2f}"
                if method == "pooled":  # the job's own run with its default position method: one user's set
                    own = pooled_predictions([{name: r[name]["one_set"]} for r in runs], name)
                    one = position_coverage(own, scorer)
                    radius += f" (one set: {radius_ratio(own, scorer):.2f})"
                    raw[label][scorer] |= {"one_set_coverage": one, "one_set_statement": [r[name]["one_set"]["one_set"] for r in runs]}
                    cells = [f"{c}; one set {fmt_share(one[str(level)])}" for c, level in zip(cells, LEVELS, strict=True)]
            else:
                coverage = position_coverage(p, scorer)
                sizes = radius_summary(p, scorer)
                cells = [f"{coverage[str(level)]:.3f}" for level in LEVELS]
                radius = f"{sizes['0.8']['median_m'] / sizes['0.8']['oracle_m']:.2f} (0.95: {sizes['0.95']['median_m']:.2f} m)"
                raw[label][scorer] = {"coverage_by_position": coverage, "radii": sizes}
            rows.append(
                f"| {site} | {label} | {scorer} | {100 * reported['share']:.1f} ({100 * reported['low']:.1f}–{100 * reported['high']:.1f}) | "
                f"{100 * solver['share']:.1f} | {reported['share'] / max(solver['share'], 1e-12):.2f} | {' | '.join(cells)} | {radius} |"
            )
    return rows, raw


def fmt_share(value: float) -> str:
    """A coverage for the table: 'no radius' where the level had none."""
    return "no radius" if np.isnan(value) else f"{value:.2f}"


def radius_ratio(predictions: pd.DataFrame, scorer: str) -> float:
    """The median 0.8 radius over the 0.8-quantile of the errors."""
    sizes = radius_summary(predictions, scorer)["0.8"]
    return sizes["median_m"] / sizes["oracle_m"]


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sites", nargs="+", default=["frozen_lake", "forest"])
    parser.add_argument("--arrays", type=int, default=2)
    parser.add_argument("--n-positions", type=int, default=100)
    parser.add_argument("--spots", type=int, default=10)
    parser.add_argument("--draws", type=int, default=2000)
    opts = parser.parse_args()
    lines = [
        "# The field workflow end to end: an impaired array, calibrated from a sweep, radii from calls at a few spots",
        "",
        f"`python experiments/field_workflow.py --sites {' '.join(opts.sites)} --arrays {opts.arrays} --n-positions {opts.n_positions} "
        f"--spots {opts.spots} --draws {opts.draws}`. Second simulator (pyroomacoustics), {opts.arrays} array draw(s) per site with "
        f"mics 2 m off per axis, clocks within ±1 ms and the thermometer 3 °C high; {opts.n_positions} positions × 5 calls per array "
        f"(30 % outside the array). **calibrated**: `calibrate` from the sweep at {opts.spots} planned spots, radii from the calls "
        f"at {opts.spots} field positions: coverage is the mean over {opts.draws} draws of those positions per array (5–95 % range of "
        "one draw), pooled over each position's calls as by default or, in the 'subsample' rows, one call drawn per position "
        "(`position_method: subsample` on each scorer), and 'one set' the job's own run with `protocol.calibration_positions` (one draw, spots in training). **without "
        "playbacks**: the stated array, radii from the simulation grown by the allowance for mics 2 m, clocks 0.58 ms, thermometer "
        "3 °C. **surveyed**: the same sources without any error. Coverage per position (the mean over positions of the share of "
        "their calls covered); > 5 m: the reported position, failures as errors, 95 % position-bootstrap interval; radius: the "
        "median 0.8 radius over the oracle's (the 0.8-quantile of the errors).",
        "",
        "| site | array | scorer | reported > 5 m % (95 % CI) | solver > 5 m % | ratio | 0.50 | 0.80 | 0.95 | 0.8 radius ÷ oracle |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    raw: dict[str, dict] = {}
    for site in opts.sites:
        runs = [array_runs(site, a, opts) for a in range(opts.arrays)]
        rows, raw[site] = site_rows(site, runs, opts)
        raw[site]["temperature_offset_c"] = [r["calibrated"]["temperature_offset_c"] for r in runs]
        lines += rows
        write_results("field_workflow", {"machine": machine(), "sites": raw}, lines)  # each site's rows as soon as they are in
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
