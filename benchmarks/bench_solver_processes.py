"""The solvers' speed-up over per-event SciPy in several fresh processes: how far one run's ratio moves.

Usage: python benchmarks/bench_solver_processes.py [--processes 8] [--n-detections 20000] [--n-scipy 500] [--rounds 5]

``bench_solver_speed.py`` times every solver in one process. A ratio measured there moves between
runs for two reasons it cannot see: SciPy's per-call cost moves with the machine's day, and the same
compiled kernel, on the same data, runs faster in some processes than in others (by several per
cent for identical code: the per-process figures below show it). This script starts ``--processes`` fresh Python
processes one after the other; each builds ``bench_solver_speed.py``'s forest detections (6 mics,
noise-free TDOAs, K = 3 candidates per pair), warms each solver up, and times ``--rounds``
interleaved rounds of SciPy on ``--n-scipy`` detections and each solver on ``--n-detections``
(the ratio within the round, as ``bench_solver_speed.py``'s rounds). Reported per solver: the median
ratio of each process, and over the processes the median, lowest and highest of those medians, of
the solver's µs per detection and of SciPy's. The solvers: the default consistent-set solver in
numpy (``solver=consistent_set``), the compiled one (``solver=consistent_set_compiled``, the
season's default) and the compiled closed form (``solver=hyperbolic_compiled``), each with its goal
from the issue (≥ 100× for the default solver with its candidate selection, ≥ 1,000× for the closed
form).

Run it alone on an idle machine: each process is one core's worth of work.

Writes benchmarks/results/solver_processes.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
from bench_solver_speed import GOAL_CLOSED_FORM, GOAL_COMPILED, GOAL_DEFAULT, GOALS, scene, scipy_per_event, timed
from common import compose_cfg, machine, write_results

from acoustlab.core.contracts import SolverInputs
from acoustlab.run.registry import build
from acoustlab.stages.sites import site_from_config

log = logging.getLogger("bench_solver_processes")

#: Solvers timed, by ``bench_solver_speed.py``'s labels of the rows with a goal (:data:`GOALS`): label -> config name.
SOLVERS = {GOAL_DEFAULT: "consistent_set", GOAL_COMPILED: "consistent_set_compiled", GOAL_CLOSED_FORM: "hyperbolic_compiled"}


def one_process(n_detections: int, n_scipy: int, rounds: int) -> dict:
    """This process's rounds: per solver the ratio of each round, its µs per detection and SciPy's (lists, one per round)."""
    site = site_from_config(compose_cfg(["+site=forest"]).site)
    _, inputs = scene(site, n_detections)
    closed_form = SolverInputs(**{k: getattr(inputs, k) for k in ("mic_positions_m", "tdoa_s", "speed_of_sound_m_s", "source_height_m")})
    solvers = {}
    for label, name in SOLVERS.items():
        solver = build(compose_cfg(["+site=forest", f"solver={name}"]).solver, "solver")
        solver_inputs = closed_form if name == "hyperbolic_compiled" else inputs
        solver.solve(solver_inputs)  # warm-up: cached designs, imports, the compiled kernels' load
        solvers[label] = (solver, solver_inputs)
    scipy_once = lambda: scipy_per_event(site.mic_positions_m, inputs.tdoa_s[:n_scipy], inputs.source_height_m)  # noqa: E731
    out = {label: {"ratio": [], "us": [], "scipy_us": []} for label in solvers}
    for _ in range(rounds):
        scipy_s = timed(scipy_once)[0] / n_scipy
        for label, (solver, solver_inputs) in solvers.items():
            solver_s = timed(solver.solve, solver_inputs)[0] / n_detections
            out[label]["ratio"].append(scipy_s / solver_s)
            out[label]["us"].append(1e6 * solver_s)
            out[label]["scipy_us"].append(1e6 * scipy_s)
    return out


def summarise(processes: list[dict]) -> dict:
    """Per solver: each process's median ratio, µs and SciPy µs, and their median, lowest and highest over the processes."""
    summary = {}
    for label in SOLVERS:
        goal = GOALS[label]
        per = {key: [float(np.median(p[label][key])) for p in processes] for key in ("ratio", "us", "scipy_us")}
        summary[label] = {"goal": goal, "per_process": per,
                          **{f"{key}_{stat}": float(fn(values)) for key, values in per.items()
                             for stat, fn in (("median", np.median), ("min", np.min), ("max", np.max))},
                          "processes_meeting_goal": int(sum(r >= goal for r in per["ratio"]))}
    return summary


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--processes", type=int, default=8)
    parser.add_argument("--n-detections", type=int, default=20000)
    parser.add_argument("--n-scipy", type=int, default=500)
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds of SciPy and the solvers in each process")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)  # one process's rounds, as JSON on stdout
    opts = parser.parse_args()
    if opts.worker:
        print(json.dumps(one_process(opts.n_detections, opts.n_scipy, opts.rounds)))
        return
    if opts.processes < 2 or opts.rounds < 1:
        raise SystemExit(f"--processes must be >= 2 and --rounds >= 1; got {opts.processes} and {opts.rounds}")
    processes = []
    for n in range(opts.processes):
        proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", "--n-detections", str(opts.n_detections),
                               "--n-scipy", str(opts.n_scipy), "--rounds", str(opts.rounds)], capture_output=True, text=True)
        if proc.returncode != 0:
            raise SystemExit(f"process {n + 1} of {opts.processes} failed:\n{proc.stderr[-3000:]}")
        processes.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        log.info("process %d/%d done", n + 1, opts.processes)
    summary = summarise(processes)
    result = {"machine": machine(), "processes": opts.processes, "n_detections": opts.n_detections, "n_scipy": opts.n_scipy,
              "rounds": opts.rounds, "solvers": summary, "raw": processes}
    lines = ["# Solver speed-up over per-event SciPy in fresh processes (forest, 6 mics)", "",
             f"`python benchmarks/bench_solver_processes.py --processes {opts.processes} --n-detections {opts.n_detections} "
             f"--n-scipy {opts.n_scipy} --rounds {opts.rounds}`: {opts.processes} fresh processes one after the other, each "
             f"{opts.rounds} interleaved rounds of SciPy on {opts.n_scipy} detections and each solver on {opts.n_detections:,} "
             "(`bench_solver_speed.py`'s detections); a process's figure is the median of its rounds, and the table gives "
             "the median, lowest and highest of those over the processes.", "",
             "| solver | speed-up: median | lowest | highest | processes at the goal | goal | µs per detection: median | lowest | highest |",
             "|---|---|---|---|---|---|---|---|---|"]
    for label, s in summary.items():
        lines.append(f"| {label} | {s['ratio_median']:.1f}× | {s['ratio_min']:.1f}× | {s['ratio_max']:.1f}× | "
                     f"{s['processes_meeting_goal']} of {opts.processes} | ≥ {s['goal']:,}× | {s['us_median']:.2f} | {s['us_min']:.2f} | "
                     f"{s['us_max']:.2f} |")
    scipy = next(iter(summary.values()))
    lines += ["", f"SciPy's `least_squares` per detection in the same processes: median {scipy['scipy_us_median']:.1f} µs, "
              f"lowest {scipy['scipy_us_min']:.1f}, highest {scipy['scipy_us_max']:.1f}."]
    write_results("solver_processes", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
