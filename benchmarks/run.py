"""Run acoustlab's speed and memory benchmarks: ``python benchmarks/run.py [NAME ...] [--quick] [--mlflow]``.

The benchmarks are declarative, in the style of asv (and scikit-learn's ``asv_benchmarks``): each
``benchmarks/bench_NAME.py`` holds classes with

- ``params`` (a list of value lists) and ``param_names``: every combination is one case;
- ``setup(self, *params)``: builds what a case needs, untimed (raise ``NotImplementedError`` to skip a
  case, e.g. a GPU case on a machine without one);
- ``time_*(self, *params)``: timed, best and median wall seconds of ``repeat`` calls after one warm-up;
- ``track_*(self, *params)``: returns a figure of its own (``unit`` attribute on the method), e.g. a
  season's detections per second measured as a user runs it;
- ``peakmem_*(self, *params)``: run with its setup in a fresh process; the figure is that process'
  peak resident memory (MiB), as asv reports it.

Results are speed and memory of this machine on this day, not history: they go to the git-ignored
``benchmarks/.results/<bench>.json`` (each run overwrites its benchmark's file, with the commit,
date and machine in it) and, with ``--mlflow``, to the project's MLflow store (experiment
``benchmarks``). Compare two versions by running both on one machine, one after the other.
``--quick`` runs each class's ``quick_params`` (or the first value of each parameter) once.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import inspect
import itertools
import json
import logging
import multiprocessing
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RESULTS = HERE / ".results"
log = logging.getLogger("benchmarks")


def machine() -> dict[str, Any]:
    """The commit, date, Python, CPU model and the cores this process may use: what a figure depends on."""
    model = platform.processor()
    if Path("/proc/cpuinfo").is_file():
        model = next(
            (line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("model name")),
            model,
        )
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    return {"commit": commit, "date": datetime.date.today().isoformat(), "python": platform.python_version(), "cpu": model, "cores": cores}


def cases(cls: type, quick: bool) -> list[tuple]:
    """The parameter combinations of a benchmark class (one empty tuple when it has no ``params``)."""
    params = getattr(cls, "quick_params", None) if quick else None
    params = params or getattr(cls, "params", None)
    if not params:
        return [()]
    if quick and not hasattr(cls, "quick_params"):
        params = [values[:1] for values in params]
    return list(itertools.product(*params))


def _peak_in_child(module: str, cls_name: str, method: str, case: tuple, queue: multiprocessing.Queue) -> None:
    """In a fresh process: setup, the method, then the process' peak RSS (VmHWM, MiB) put on ``queue``."""
    sys.path.insert(0, str(HERE))
    bench = getattr(importlib.import_module(module), cls_name)()
    bench.setup(*case)
    getattr(bench, method)(*case)
    status = Path("/proc/self/status").read_text().splitlines()
    queue.put(int(next(line.split()[1] for line in status if line.startswith("VmHWM"))) / 1024)


def measure(module: str, bench: Any, method: str, case: tuple, repeat: int) -> dict[str, Any]:
    """One figure of one case: seconds for ``time_*``, the returned value for ``track_*``, MiB for ``peakmem_*``."""
    fn = getattr(bench, method)
    if method.startswith("time_"):
        fn(*case)  # warm-up: imports, caches and any compilation are not the steady state
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            fn(*case)
            times.append(time.perf_counter() - start)
        return {"unit": "s", "best": min(times), "median": statistics.median(times), "repeat": repeat}
    if method.startswith("track_"):
        return {"unit": getattr(fn, "unit", ""), "value": float(fn(*case))}
    ctx = multiprocessing.get_context("spawn")  # a forked child would inherit this process' high-water mark
    queue = ctx.Queue()
    child = ctx.Process(target=_peak_in_child, args=(module, type(bench).__name__, method, case, queue))
    child.start()
    child.join()
    if child.exitcode != 0:
        raise RuntimeError(f"{module}.{type(bench).__name__}.{method}{case} failed in its own process (exit {child.exitcode})")
    return {"unit": "MiB", "value": queue.get()}


def run_module(name: str, quick: bool, repeat: int, only: set[str] | None = None) -> list[dict[str, Any]]:
    """Every case of every benchmark class in ``benchmarks/bench_<name>.py`` (of the classes in ``only``, when given)."""
    module = importlib.import_module(f"bench_{name}")
    rows = []
    for cls_name, cls in inspect.getmembers(module, inspect.isclass):
        if cls.__module__ != module.__name__ or (only and cls_name not in only):
            continue
        methods = [m for m in dir(cls) if m.startswith(("time_", "track_", "peakmem_"))]
        for case in cases(cls, quick):
            bench = cls()
            labels = dict(zip(getattr(cls, "param_names", []), case, strict=False))
            try:
                bench.setup(*case)
            except NotImplementedError as why:
                log.info("skip %s %s: %s", cls_name, labels, why)
                continue
            for method in methods:
                figure = measure(module.__name__, bench, method, case, 1 if quick else repeat)
                rows.append({"benchmark": f"{name}.{cls_name}.{method}", "params": labels, **figure})
                shown = figure.get("value", figure.get("best"))
                log.info("%-50s %-40s %12.4g %s", f"{cls_name}.{method}", labels, shown, figure["unit"])
            if hasattr(bench, "teardown"):
                bench.teardown(*case)
    return rows


def log_to_mlflow(name: str, rows: list[dict[str, Any]], about: dict[str, Any]) -> None:
    """Each figure as an MLflow metric of one run in the project's store (experiment ``benchmarks``)."""
    import mlflow

    mlflow.set_tracking_uri(f"sqlite:///{REPO / 'outputs' / 'mlflow.db'}")
    mlflow.set_experiment("benchmarks")
    with mlflow.start_run(run_name=name):
        mlflow.set_tags(about)
        for i, row in enumerate(rows):
            key = row["benchmark"] + "".join(f".{k}={v}" for k, v in row["params"].items())
            mlflow.log_metric(key.replace("=", "_")[:250], row.get("value", row.get("best")), step=i)


def main(argv: list[str] | None = None) -> int:
    names = sorted(p.stem.removeprefix("bench_") for p in HERE.glob("bench_*.py"))
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "names", nargs="*", metavar="NAME", help=f"benchmarks to run, NAME or NAME.Class (default: all): {', '.join(names)}"
    )
    parser.add_argument("--quick", action="store_true", help="one small case per benchmark class, once (checks that they run)")
    parser.add_argument("--repeat", type=int, default=5, help="timed calls per time_* case")
    parser.add_argument("--mlflow", action="store_true", help="also log the figures to outputs/mlflow.db (experiment 'benchmarks')")
    opts = parser.parse_args(argv)
    wanted: dict[str, set[str]] = {}
    for given in opts.names:
        name, _, cls_name = given.partition(".")
        if name not in names:
            parser.error(f"no benchmark named {name!r}; there are: {', '.join(names)}")
        wanted.setdefault(name, set()).update([cls_name] if cls_name else [])
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sys.path.insert(0, str(HERE))
    about = machine()
    for name in wanted or names:
        rows = run_module(name, opts.quick, opts.repeat, wanted.get(name))
        RESULTS.mkdir(exist_ok=True)
        out = RESULTS / f"{name}.json"
        out.write_text(
            json.dumps(
                {
                    "command": " ".join(["python", "benchmarks/run.py", *(argv or sys.argv[1:])]),
                    **about,
                    "quick": opts.quick,
                    "results": rows,
                },
                indent=1,
            )
        )
        log.info("wrote %s", out)
        if opts.mlflow:
            log_to_mlflow(name, rows, about)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
