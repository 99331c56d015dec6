"""Real 6-recorder array (LOCA 2021, shipped example; no ground truth): TDOAs, a position, and a
check that needs no ground truth — leave one receiver out, predict its TDOA from the others.

Usage: python experiments/real_array.py
Writes experiments/results/real_array.md. The GCC band is limited to the call's
6–10.5 kHz (the recording has a strong insect band near 4.5 kHz), as one would with any tool.
The fix is 3-D (``solver.dimensions=3``: x, y and height in closed form with a polish; the array's
recorders sit at different heights). As a cross-check the 2-D solver's assumed height is scanned
over 0–400 m (flight calls come from birds aloft) and the best-fitting height kept.
"""

from __future__ import annotations

import argparse
import logging

import numpy as np
from common import compose_cfg, write_results

from acoustlab.core.contracts import SolverInputs
from acoustlab.run.registry import build, build_feature_sets
from acoustlab.stages.dataset import extract_features
from acoustlab.stages.sites import site_from_config
from acoustlab.stages.solver_columns import tdoa_matrix
from acoustlab.toolkit.physics import speed_of_sound_m_s
from plugins.solvers.hyperbolic import HyperbolicSolver

log = logging.getLogger("experiments.real_array")
BAND = "[6000,10500]"
UPSTREAM_TDOA_S = [0.0, 0.0325, -0.002, 0.0316, -0.0086, 0.024]  # OpenSoundscape's test reference, ±0.01 s


def solve_scan(
    mics: np.ndarray, tdoa: np.ndarray, c: float, heights=np.concatenate([np.arange(0.0, 50.0, 0.5), np.arange(50.0, 400.0, 2.0)])
):
    best = None
    for h in heights:
        res = HyperbolicSolver(source_height_m=float(h), box_margin_fraction=3.0).solve(SolverInputs(mics, tdoa, c))
        if best is None or res.residual_m[0] < best[1].residual_m[0]:
            best = (h, res)
    return best


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    overrides = [f"features.gcc.band_hz={BAND}"]  # one GCC band for the tdoa, xcorr and uncertainty groups
    cfg = compose_cfg(["+site=loca2021", "field=recordings", *overrides])
    site = site_from_config(cfg.site)
    batch = build(cfg.field, "field").load(site)
    table = extract_features(batch, site, build_feature_sets(cfg.features))
    tdoa = tdoa_matrix(table, site.n_mics)
    c = float(speed_of_sound_m_s(15.0, 60.0))
    mics = site.mic_positions_m
    res = HyperbolicSolver(dimensions=3).solve(SolverInputs(mics, tdoa, c))
    height = float(res.diagnostics["source_height_m"][0])
    scan_height, scan = solve_scan(mics, tdoa, c)
    loo = []
    for r in range(site.n_mics):
        keep = [m for m in range(site.n_mics) if m != r]
        ref = keep[0]
        sub_tdoa = tdoa[:, keep] - tdoa[:, [ref]]
        # every 3-D fix kept: leaving recorder 3 out puts the five-receiver fix 43 m north at 200 m height, outside the
        # mics' box grown by the array extent, where the default 2-D fallback (9.9 m height, 6 m residual) would replace it
        sub = HyperbolicSolver(dimensions=3, fallback_2d=False).solve(SolverInputs(mics[keep], sub_tdoa, c))
        with_fallback = HyperbolicSolver(dimensions=3).solve(SolverInputs(mics[keep], sub_tdoa, c))
        src = np.array([sub.position_m[0, 0], sub.position_m[0, 1], sub.diagnostics["source_height_m"][0]])
        dist = np.linalg.norm(mics - src, axis=1)
        predicted = (dist[r] - dist[ref]) / c
        measured = tdoa[0, r] - tdoa[0, ref]
        loo.append(
            {
                "left_out": r,
                "reference": ref,
                "measured_ms": 1e3 * measured,
                "predicted_ms": 1e3 * predicted,
                "error_ms": 1e3 * (predicted - measured),
                "fix_m": src.tolist(),
                "fallback_kept_3d": bool(with_fallback.diagnostics["dimensions_used"][0] == 3),
            }
        )
    result = {
        "measured_tdoa_s": tdoa[0].tolist(),
        "upstream_reference_tdoa_s": UPSTREAM_TDOA_S,
        "max_abs_diff_to_upstream_ms": float(1e3 * np.max(np.abs(tdoa[0] - UPSTREAM_TDOA_S))),
        "position_m": [float(res.position_m[0, 0]), float(res.position_m[0, 1]), float(height)],
        "height_gdop": float(res.diagnostics["height_gdop"][0]),
        "height_ambiguous": bool(res.diagnostics["height_ambiguous"][0]),
        "scanned_2d": {
            "position_m": [float(scan.position_m[0, 0]), float(scan.position_m[0, 1]), float(scan_height)],
            "residual_m": float(scan.residual_m[0]),
        },
        "residual_m": float(res.residual_m[0]),
        "gdop": float(res.diagnostics["gdop"][0]),
        "leave_one_receiver_out": loo,
        "loo_rms_error_ms": float(np.sqrt(np.mean([x["error_ms"] ** 2 for x in loo]))),
    }
    lines = [
        "# Real array: LOCA 2021 (6 recorders, one call, no ground truth)",
        "",
        "`python experiments/real_array.py` (GCC-PHAT band 6–10.5 kHz, 3-D hyperbolic solver: x, y and height, no scan)",
        "",
        "TDOA to recorder 3 (ms): "
        + ", ".join(f"{1e3 * v:.1f}" for v in tdoa[0])
        + " — OpenSoundscape's reference: "
        + ", ".join(f"{1e3 * v:.1f}" for v in UPSTREAM_TDOA_S)
        + f" (largest difference {result['max_abs_diff_to_upstream_ms']:.2f} ms; its tests allow ±10 ms).",
        "",
        f"3-D fix: x = {result['position_m'][0]:.1f} m, y = {result['position_m'][1]:.1f} m, height "
        f"{height:.1f} m (height GDOP {result['height_gdop']:.1f}: 1 m of range-difference error is "
        f"{result['height_gdop']:.1f} m of height; mirror ambiguous: {result['height_ambiguous']}); "
        f"RMS range-difference residual {result['residual_m']:.2f} m; GDOP {result['gdop']:.2f}.",
        "",
        f"Cross-check, 2-D solver with its assumed height scanned over 0–400 m: x = {result['scanned_2d']['position_m'][0]:.1f} m, "
        f"y = {result['scanned_2d']['position_m'][1]:.1f} m, best-fitting height {scan_height:.1f} m, residual "
        f"{result['scanned_2d']['residual_m']:.2f} m.",
        "",
        "Leave one receiver out (locate in 3-D with the other five, every 3-D fix kept, and predict the left-out receiver's TDOA). "
        "The last column says whether the solver's default 2-D fallback (a 3-D fix outside the mics' box grown by the array "
        "extent is replaced by the 2-D fix at the assumed height) would have kept that fix; where it would not, the fallback's "
        "prediction is far worse (left out 3: 29 ms, which is what made an earlier version of this file read 11.9 ms RMS).",
        "",
        "| left out | reference | measured (ms) | predicted (ms) | error (ms) | fix x, y, height (m) | default fallback keeps it |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {x['left_out']} | {x['reference']} | {x['measured_ms']:.2f} | {x['predicted_ms']:.2f} | {x['error_ms']:+.2f} | "
        f"{x['fix_m'][0]:.1f}, {x['fix_m'][1]:.1f}, {x['fix_m'][2]:.0f} | {'yes' if x['fallback_kept_3d'] else 'no'} |"
        for x in loo
    ]
    lines += ["", f"RMS error {result['loo_rms_error_ms']:.2f} ms (1 ms ≈ 0.34 m of range difference)."]
    write_results("real_array", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
