"""``python -m acoustlab.upload RUN_DIR ...``: send run directories to the experiment tracker after the fact.

The tracker is rebuilt from each run's ``config_resolved.yaml``; a run that was not tracked
(``tracking=none``) is sent with the registered MLflow option (``conf/tracking/mlflow.yaml``).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from acoustlab.core.errors import AcoustlabError, ConfigError
from acoustlab.reporting.experiment_log import PENDING_FILE, log_run_dir
from acoustlab.run.registry import CONF_DIR, build

log = logging.getLogger(__name__)
#: The tracking option used for runs whose own config tracked nothing.
DEFAULT_TRACKING_OPTION = "mlflow"


def tracker_for(run_dir: Path, tracking_uri: str | None, experiment: str | None) -> Any:
    """The tracker a run directory's config names (MLflow when it named none), with overrides applied."""
    config_file = run_dir / "config_resolved.yaml"
    if not config_file.exists():
        raise ConfigError(f"{config_file} is missing: {run_dir} is not an acoustlab run directory")
    run_cfg = OmegaConf.load(config_file)
    node = run_cfg.get("tracking")
    if node is None or "_target_" not in node or getattr(build(node, "tracking"), "destination", None) is None:
        node = OmegaConf.load(CONF_DIR / "tracking" / f"{DEFAULT_TRACKING_OPTION}.yaml")
        node.store_dir = str(run_cfg.get("paths", {}).get("outputs_dir", "outputs"))
    if tracking_uri:
        node.tracking_uri = tracking_uri
    if experiment:
        node.experiment_name = experiment
    return build(node, "tracking")


def main(argv: list[str] | None = None) -> int:
    """``python -m acoustlab.upload RUN_DIR ... [--tracking-uri URI] [--experiment NAME]``."""
    parser = argparse.ArgumentParser(prog="python -m acoustlab.upload", description="Upload run directories to MLflow (e.g. after the server was unreachable).")
    parser.add_argument("run_dirs", nargs="+", type=Path, help="run directories (holding metrics.json), or folders searched for them")
    parser.add_argument("--tracking-uri", help="MLflow tracking URI; default: the one in each run's config_resolved.yaml")
    parser.add_argument("--experiment", help="MLflow experiment name; default: the run's own")
    parser.add_argument("--only-pending", action="store_true", help=f"upload only runs marked with {PENDING_FILE}")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    run_dirs = []
    for path in args.run_dirs:
        if not path.exists():
            print(f"acoustlab.upload: error: {path} does not exist", file=sys.stderr)
            return 2
        found = [path] if (path / "metrics.json").exists() else sorted(p.parent for p in path.rglob("metrics.json"))
        run_dirs += [d for d in found if not args.only_pending or (d / PENDING_FILE).exists()]
    if not run_dirs:
        print(f"acoustlab.upload: error: no run directories (with metrics.json) under {', '.join(map(str, args.run_dirs))}", file=sys.stderr)
        return 2
    failed = 0
    for run_dir in run_dirs:
        try:
            tracker = tracker_for(run_dir, args.tracking_uri, args.experiment)
        except AcoustlabError as exc:
            print(f"acoustlab.upload: error: {exc}", file=sys.stderr)
            return 2
        failed += not log_run_dir(tracker, run_dir)
    log.info("uploaded %d of %d run directories", len(run_dirs) - failed, len(run_dirs))
    return 1 if failed else 0
