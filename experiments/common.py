"""Helpers shared by the experiments: compose the real config, run a job in this process, write one result file."""

from __future__ import annotations

import datetime
import json
import logging
import math
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra

from acoustlab.run.registry import CONF_DIR

REPO = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"
log = logging.getLogger("experiments")


def time_cli(args: list[str]) -> float:
    """Seconds one ``python -m acoustlab ARGS`` command takes in a fresh process, imports included.

    Raises
    ------
    SystemExit
        With the command and the end of its stderr when it fails.
    """
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "acoustlab", *args], cwd=REPO, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"command failed: {args}\n{proc.stderr[-3000:]}")
    log.info("%6.1f s  %s", elapsed, " ".join(args))
    return elapsed


def compose_cfg(overrides: list[str]):
    """The composed acoustlab config for ``overrides``."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=overrides)


def machine() -> dict[str, Any]:
    """A short description of the machine the numbers were measured on."""
    import os

    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    # "cpus": the cores this process may run on (a benchmark pinned with taskset reports its share, not the machine's)
    return {"python": platform.python_version(), "machine": platform.machine(), "cpus": usable, "machine_cpus": os.cpu_count()}


#: Distributions whose releases can move a result (numerics, learned models, configs); their versions go into every result.
PACKAGES = (
    "numpy",
    "scipy",
    "pandas",
    "pyarrow",
    "scikit-learn",
    "xgboost",
    "xgboost-cpu",
    "torch",
    "tabpfn",
    "soundfile",
    "hydra-core",
    "omegaconf",
)


def package_versions() -> dict[str, str]:
    """Installed versions of ``PACKAGES`` (those not installed are left out)."""
    from importlib import metadata

    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return versions


def _git(*args: str) -> str:
    proc = subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True)
    return proc.stdout.strip() if proc.returncode == 0 else ""


#: the paths whose content decides what a run predicts
CODE_PATHS = ("acoustlab", "conf", "plugins")


def code_version() -> str:
    """The git tree ids of the code a run executes (``CODE_PATHS`` at HEAD); '' where they have uncommitted changes.

    Kept predictions are reused only when it matches, so a result headed by a commit is never made
    from predictions an older code made (a commit of docs or results alone keeps them).
    """
    if _git("status", "--porcelain", "--untracked-files=no", "--", *CODE_PATHS):
        return ""
    return " ".join(_git("rev-parse", f"HEAD:{path}") for path in CODE_PATHS)


def provenance() -> dict[str, Any]:
    """What made a result: the command line, the commit (and whether the work tree had changes), the day, the packages.

    Two runs of the same commit can differ where a package release changed (an XGBoost or scikit-learn
    update moves the learned models' figures): ``packages`` says which releases made this one.
    """

    script = Path(sys.argv[0]).resolve()
    shown = script.relative_to(REPO).as_posix() if script.is_relative_to(REPO) else str(script)
    changes = _git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)experiments/results")
    return {
        "command": shlex.join(["python", shown, *sys.argv[1:]]),  # quoted as a shell needs it, to be run again as it stands
        "commit": _git("rev-parse", "HEAD"),
        "uncommitted_changes": bool(changes),
        "date": datetime.date.today().isoformat(),
        "packages": package_versions(),
    }


def write_results(name: str, result: dict[str, Any], markdown: list[str]) -> Path:
    """Write ``results/<name>.md``, overwriting the last run's: the tables, headed by the command, commit and day that made them.

    The raw result (``result`` and its provenance) follows the tables as a JSON block, so the file is the
    one record of the run. ``markdown[0]`` is the page's title.
    """
    RESULTS.mkdir(parents=True, exist_ok=True)
    made_with = provenance()
    dirty = " plus uncommitted changes" if made_with["uncommitted_changes"] else ""
    header = [
        markdown[0],
        "",
        f"> Made by `{made_with['command']}` at commit {made_with['commit'][:10]}{dirty} on {made_with['date']}. "
        "Re-running the command overwrites this file.",
    ]
    raw = json.dumps({**result, "provenance": made_with}, indent=1, default=float)
    path = RESULTS / f"{name}.md"
    path.write_text(
        "\n".join(
            [*header, *markdown[1:], "", "<details><summary>Raw result (JSON)</summary>", "", "```json", raw, "```", "", "</details>"]
        )
        + "\n"
    )
    log.info("wrote %s", path)
    return path


def run_in_process(overrides: list[str], keep: Path | None = None) -> dict[str, Any]:
    """One acoustlab job in this process (``tracking=none``, no plots): its metrics, with ``bench_seconds``.

    With ``keep`` its predictions.parquet is copied there (e.g. under outputs/, not committed) for a closer look.
    """
    from acoustlab.run.app import run_experiment  # imported when a benchmark runs a job, not by every script importing this module

    cfg = compose_cfg([*overrides, "tracking=none", "plots=false"])
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        metrics = run_experiment(cfg, Path(tmp) / "run", {})
        metrics["bench_seconds"] = time.perf_counter() - start
        if keep is not None:
            keep.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(Path(tmp) / "run" / "predictions.parquet", keep)
        return metrics


def fmt(v: float | None) -> str:
    """A metric for a Markdown table: '—' for a missing value, '∞' for a failure, 2 decimals below 10, none above."""
    if v is None or math.isnan(v):
        return "—"
    if v == float("inf"):
        return "∞"
    return f"{v:.2f}" if v < 10 else f"{v:.0f}"
