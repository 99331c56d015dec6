"""Do radii calibrated on the playbacks that calibrated the array hold at new spots? In-sample vs held out vs fresh spots.

Usage: python experiments/radii_leak.py [--replications 200] [--spots 10 20] [--mics 3 6]

Synthetic playbacks, the project's own calibration (``CalibrateProtocol``: thermometer, clocks,
mic positions within their stated 2 m) and solver (``HyperbolicSolver``). Per replication: mics on
a 30 m circle, each stated 2 m from where it stands, clocks within ±1 ms, the thermometer 3 °C
high; K spots × 3 playbacks calibrate the array; the fixes' errors of those playbacks calibrate
split-conformal radii (the ⌈(n+1)ℓ⌉-th smallest error, pooled over the playbacks), three ways:

* **in-sample**: the playbacks solved with the array fitted on them (what ``localize`` did before);
* **held out**: each spot's playbacks solved with the array calibrated without that spot
  (``calibration.json``'s ``held_out_arrays``, what ``localize`` does now);
* **fresh spots**: K other spots × 3 playbacks solved with the full calibration (the reference:
  radii calibrated on spots the array never saw).

Coverage is measured at 50 new spots × 3 calls solved with the full calibration, per position (the
mean over spots of the share of their calls covered), and averaged over replications. Three timing
noise kinds: white (20 µs per mic and call), per-spot multipath (a 60 µs delay per mic and spot
shared by its playbacks, plus 10 µs white), heavy-tailed (Student t, 3 degrees of freedom, 20 µs);
and for ``calibration_sigma.py`` a ground reflection merged with every direct path (the peak moved
by ``REFLECTION_FRACTION`` of ``toolkit.ground_reflection``'s shift in a 0.5–2 kHz band: a bias every
spot shares, plus 10 µs white). Writes experiments/results/radii_leak.md.
"""

from __future__ import annotations

import argparse
import itertools
import logging

import numpy as np
from common import write_results

from acoustlab.core.types import NoiseRegime, Site
from acoustlab.method.protocols.calibrate import CalibrateProtocol, _solve_errors
from acoustlab.toolkit.array_calibration import Playbacks, Priors
from acoustlab.toolkit.conformal import conformal_quantile
from acoustlab.toolkit.ground_reflection import peak_shift_per_fraction_s, reflection_delay_s
from acoustlab.toolkit.physics import speed_of_sound_m_s
from acoustlab.toolkit.recorder_clocks import clock_errors_s

log = logging.getLogger("experiments.radii_leak")
LEVELS = (0.5, 0.8, 0.95)
NOISES = ("white", "multipath", "heavy")
SCHEMES = ("in-sample", "held out", "fresh spots")
PER = 3
#: the "reflection" noise: a hard ground's reflection merged with the direct path, the peaks measured in a low band (Hz)
REFLECTION_FRACTION, REFLECTION_BAND_HZ = 0.35, (500.0, 2000.0)


def site_of(mics_m: np.ndarray) -> Site:
    """A bare site around the stated mics (only the geometry and the assumed source height matter here)."""
    return Site(
        "leak", mics_m, np.zeros((0, 2)), np.zeros(0), (12, 12), (70, 70), "x", 100.0, "rigid", None,
        (NoiseRegime("white"),), (10, 10), ("synthetic",), (1.5, 1.5), 0.2,
    )  # fmt: skip


def playbacks(rng, true_mics, spots, clocks, noise: str, first_spot: int) -> Playbacks:
    """``PER`` playbacks per spot heard by the true array, read with a thermometer 3 °C high."""
    source = np.repeat(spots, PER, axis=0)
    n, m = len(source), len(true_mics)
    thermometer, humidity = np.full(n, 12.0), np.full(n, 70.0)
    speed = speed_of_sound_m_s(thermometer - 3.0, humidity)
    arrival = np.sqrt(((source[:, None, :] - true_mics[None]) ** 2).sum(-1)) / speed[:, None] + clocks[None, :]
    if noise == "white":
        arrival += rng.normal(0, 2e-5, (n, m))
    elif noise == "multipath":
        arrival += np.repeat(rng.normal(0, 6e-5, (len(spots), m)), PER, axis=0) + rng.normal(0, 1e-5, (n, m))
    elif noise == "reflection":  # the ground reflection within the direct path's peak: the same fraction at every spot
        delay = reflection_delay_s(source, true_mics, speed)
        arrival += REFLECTION_FRACTION * peak_shift_per_fraction_s(delay, REFLECTION_BAND_HZ) + rng.normal(0, 1e-5, (n, m))
    else:
        arrival += 2e-5 * rng.standard_t(3, (n, m))
    pairs = list(itertools.combinations(range(m), 2))
    first, second = np.array(pairs).T
    spot = np.repeat(np.arange(first_spot, first_spot + len(spots)), PER)
    return Playbacks(source, arrival[:, second] - arrival[:, first], thermometer, humidity, np.zeros(n), spot, pairs)


def circle_array(rng: np.random.Generator, n_mics: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true, stated, clocks): mics on a 30 m circle, each stated 2 m from where it stands, clocks within ±1 ms (mic 0's 0)."""
    angle = 2 * np.pi * np.arange(n_mics) / n_mics
    true = np.column_stack([30 * np.cos(angle), 30 * np.sin(angle), np.full(n_mics, 1.5)])
    direction = rng.uniform(0, 2 * np.pi, n_mics)
    stated = true + 2.0 * np.column_stack([np.cos(direction), np.sin(direction), np.zeros(n_mics)])
    return true, stated, np.r_[0.0, rng.uniform(-1e-3, 1e-3, n_mics - 1)]


def spots_in_circle(rng: np.random.Generator, k: int) -> np.ndarray:
    """(k, 3) spots uniform over the disc of radius 25 m inside the array, 1.5 m high."""
    r, a = 25 * np.sqrt(rng.uniform(0, 1, k)), rng.uniform(0, 2 * np.pi, k)
    return np.column_stack([r * np.cos(a), r * np.sin(a), np.full(k, 1.5)])


def replication(seed: int, n_mics: int, n_spots: int, noise: str) -> dict[str, np.ndarray]:
    """Per scheme, the (levels,) per-position coverage at the new spots of one replication."""
    rng = np.random.default_rng(seed)
    true, stated, clocks = circle_array(rng, n_mics)

    def spots(k: int) -> np.ndarray:
        return spots_in_circle(rng, k)

    site = site_of(stated)
    solver = _solver()
    protocol = CalibrateProtocol(held_out_folds=10)
    priors = Priors(stated, np.full(n_mics, 2.0))
    ids = [str(k) for k in range(n_mics)]
    calibration_pb = playbacks(rng, true, spots(n_spots), clocks, noise, 0)
    fresh_pb = playbacks(rng, true, spots(n_spots), clocks, noise, 1000)
    test_pb = playbacks(rng, true, spots(50), clocks, noise, 2000)
    full = protocol.calibrate(calibration_pb, priors, ids)
    *_, arrays = protocol.held_out(calibration_pb, priors, ids, site, solver)

    def errors(p: Playbacks, mics, clock_offset, drift, origin, temperature_offset) -> np.ndarray:
        return _solve_errors(p, mics, clock_errors_s(clock_offset, drift, origin, p.time_s), temperature_offset, site, solver)

    def with_full(p: Playbacks) -> np.ndarray:
        return errors(p, full.mic_positions_m, full.clock_offset_s, full.clock_drift, full.drift_origin_s, full.temperature_offset_c)

    held = np.full(len(calibration_pb.spot), np.nan)
    for a in arrays:
        rows = np.isin(calibration_pb.spot.astype(str), a["without_spots"])
        held[rows] = errors(
            calibration_pb.subset(rows),
            np.asarray(a["mic_positions_m"]),
            np.asarray(a["clock_offset_s"]),
            np.asarray(a["clock_drift_s_per_s"]),
            a["drift_origin_s"],
            a["temperature_offset_c"],
        )
    scores = {"in-sample": with_full(calibration_pb), "held out": held, "fresh spots": with_full(fresh_pb)}
    test = np.nan_to_num(with_full(test_pb), nan=np.inf)  # a failed fix is an error no radius covers
    out = {}
    for scheme, s in scores.items():
        radii = np.array([conformal_quantile(np.nan_to_num(s, nan=np.inf), lv) for lv in LEVELS])
        covered = test[:, None] <= radii[None, :]  # (calls, levels)
        by_spot = np.array([covered[test_pb.spot == k].mean(axis=0) for k in np.unique(test_pb.spot)])
        out[scheme] = np.r_[by_spot.mean(axis=0), np.median(radii[1])]
    return out


def _solver():
    from plugins.solvers.hyperbolic import HyperbolicSolver  # the plugins folder is on the path when run from the repository

    return HyperbolicSolver()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replications", type=int, default=200)
    parser.add_argument("--spots", type=int, nargs="+", default=[10, 20])
    parser.add_argument("--mics", type=int, nargs="+", default=[3, 6])
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("acoustlab").setLevel(logging.ERROR)
    rows, raw = [], []
    for n_mics, n_spots, noise in itertools.product(args.mics, args.spots, NOISES):
        results = [replication(10_000 * n_mics + 100 * n_spots + r, n_mics, n_spots, noise) for r in range(args.replications)]
        mean = {scheme: np.mean([res[scheme] for res in results], axis=0) for scheme in SCHEMES}
        log.info("%d mics, %d spots, %s: %s", n_mics, n_spots, noise, {k: np.round(v, 3).tolist() for k, v in mean.items()})
        raw.append({"mics": n_mics, "spots": n_spots, "noise": noise, **{k: v.tolist() for k, v in mean.items()}})
        gap = np.abs(mean["held out"][:3] - mean["fresh spots"][:3]).max()
        for scheme in SCHEMES:
            cells = " | ".join(f"{v:.2f}" for v in mean[scheme][:3])
            rows.append(f"| {n_mics} | {n_spots} | {noise} | {scheme} | {cells} | {mean[scheme][3]:.2f} | {gap:.2f} |")
    markdown = [
        "# Radii after calibrate: calibrated in-sample, held out by spot, or on fresh spots (synthetic playbacks)",
        "",
        f"`python experiments/radii_leak.py --replications {args.replications}`. Coverage per position at 50 new spots × 3 "
        f"calls, the mean over {args.replications} replications per row; radii pooled over the K spots × 3 playbacks. "
        "'|held − fresh|': the largest gap over the three levels between the held-out radii and radii from fresh spots.",
        "",
        "| mics | spots | noise | radii calibrated | 0.50 | 0.80 | 0.95 | mean 0.80 radius (m) | \\|held − fresh\\| |",
        "|---|---|---|---|---|---|---|---|---|",
        *rows,
    ]
    write_results("radii_leak", {"replications": args.replications, "cells": raw}, markdown)


if __name__ == "__main__":
    main()
