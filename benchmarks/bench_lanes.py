"""The compiled selection's pair tables in vector lanes, on and off, side by side in one run, by array size.

Usage: python benchmarks/bench_lanes.py [--n-events 2000] [--rounds 5]

With three candidates per pair the compiled candidate selection
(:mod:`plugins.solvers.consistent_select`) computes the pair tables of ``LANES`` events at once,
the events innermost, up to ``_LANE_BYTES`` of tables (arrays of up to 14 mics); larger arrays
build each event's tables on its own. This benchmark times both on the same events: the module
as installed (lanes on) against a copy of its source compiled with ``_LANE_BYTES = 0`` (every
event's tables on their own, the code path of arrays too large for the lanes), in a temporary
folder with its own compiled cache.

Events: the forest's 6 mics (the solver_speed detections: noise-free TDOAs, the true lag and two
spurious peaks per pair) and the larger synthetic arrays of 8, 10 and 12 mics of solver_speed's
candidate-search table (the true lag at a random rank, random heights). Each size is timed in
calls of 4,096 events (what the compiled solver passes, ``chunk_events``) and of 16 (what
solver_speed's table passes: a block of lanes then holds 16 events). Every round times lanes on,
then off, on the same events; reported is the median of ``--rounds`` rounds, µs per event, the
ratio off / on (> 1: the lanes are faster), and whether both chose the same bit for bit.

Writes benchmarks/results/lanes.{json,md}.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench_solver_speed import large_array, scene, timed
from common import compose_cfg, machine, write_results

import plugins.solvers.consistent_select as lanes_on
from acoustlab.stages.sites import site_from_config
from plugins.solvers.consistent_set_compiled import CompiledConsistentSetSolver

log = logging.getLogger("bench_lanes")
CHUNKS = (4096, 16)


def module_without_lanes(folder: Path):
    """A copy of :mod:`plugins.solvers.consistent_select` compiled with ``_LANE_BYTES = 0`` (no array fills the lanes)."""
    source = Path(lanes_on.__file__).read_text()
    line = "_LANE_BYTES = 8 * 2**20"
    if source.count(line) != 1:
        raise SystemExit(f"bench_lanes: expected one line {line!r} in {lanes_on.__file__}; update this benchmark")
    path = folder / "consistent_select_lanes_off.py"
    path.write_text(source.replace(line, "_LANE_BYTES = 0"))
    spec = importlib.util.spec_from_file_location("consistent_select_lanes_off", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def events(n_mics: int, n_events: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidates and heights (E, P, 3): the forest's solver_speed detections for 6 mics, else solver_speed's larger arrays."""
    if n_mics == 6:
        _, inputs = scene(site_from_config(compose_cfg(["+site=forest"]).site), n_events)
        return inputs.pair_lag_candidates_s, inputs.pair_lag_weights
    _, cands, weights = large_array(n_mics, n_events)
    return cands, weights


def select_in_calls(module, cands: np.ndarray, weights: np.ndarray, chunk: int, settings: dict) -> None:
    """``module.select_compiled`` over every event, ``chunk`` events per call."""
    for i in range(0, len(cands), chunk):
        module.select_compiled(cands[i:i + chunk], weights[i:i + chunk], None, **settings)


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-events", type=int, default=2000)
    parser.add_argument("--rounds", type=int, default=5)
    opts = parser.parse_args()
    solver = CompiledConsistentSetSolver()
    settings = dict(k=3, tolerance_s=solver.tolerance_s, prior_weight=0.0, prior_tolerance_s=solver.prior_tolerance_s)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        lanes_off = module_without_lanes(Path(folder))
        for n_mics in (6, 8, 10, 12):
            cands, weights = events(n_mics, opts.n_events)
            chosen = [m.select_compiled(cands, weights, None, **settings) for m in (lanes_on, lanes_off)]  # also the warm-up
            same = all(np.array_equal(chosen[0][key], chosen[1][key], equal_nan=True) for key in chosen[0])
            for chunk in CHUNKS:
                seconds = {"on": [], "off": []}
                for _ in range(opts.rounds):
                    for label, module in (("on", lanes_on), ("off", lanes_off)):
                        seconds[label].append(timed(select_in_calls, module, cands, weights, chunk, settings)[0])
                on, off = (1e6 * float(np.median(seconds[label])) / len(cands) for label in ("on", "off"))
                rows.append({"n_mics": n_mics, "chunk_events": chunk, "us_per_event_lanes_on": on, "us_per_event_lanes_off": off,
                             "off_over_on": off / on, "same_choice_bit_for_bit": same,
                             "lane_table_bytes": n_mics * (n_mics * (n_mics - 1) // 2) * 9 * lanes_on.LANES * 8})
                log.info("%d mics, calls of %d: on %.2f µs, off %.2f µs (%.2fx), same %s", n_mics, chunk, on, off, off / on, same)
    result = {"machine": machine(), "n_events": opts.n_events, "rounds": opts.rounds, "lanes": lanes_on.LANES,
              "lane_bytes_cap": lanes_on._LANE_BYTES, "rows": rows}
    lines = ["# The compiled selection's pair tables in lanes, on and off (one run)", "",
             f"`python benchmarks/bench_lanes.py --n-events {opts.n_events} --rounds {opts.rounds}`: the compiled candidate selection alone, "
             f"{lanes_on.LANES} lanes (on, as installed) against the same module compiled with `_LANE_BYTES = 0` (off: each event's tables "
             f"on their own); median of {opts.rounds} interleaved rounds, µs per event; 6 mics: the forest's solver_speed detections, "
             "8–12: solver_speed's larger arrays.", "",
             "| mics | events per call | lanes on, µs / event | lanes off, µs / event | off / on | lane tables (MB) | same choice, bit for bit |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['n_mics']} | {r['chunk_events']:,} | {r['us_per_event_lanes_on']:.2f} | {r['us_per_event_lanes_off']:.2f} | "
                     f"{r['off_over_on']:.2f}× | {r['lane_table_bytes'] / 1e6:.2f} | {'yes' if r['same_choice_bit_for_bit'] else 'no'} |")
    write_results("lanes", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
