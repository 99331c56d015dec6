"""``python -m acoustlab.upload RUN_DIR ...``: send run directories to the experiment tracker after the fact.

A received run folder supplies data only. The tracker is always the uploader's own
(``conf/tracking/mlflow.yaml`` of this installation); nothing named in the folder's
``config_resolved.yaml`` is instantiated (a ``_target_`` there could name any callable) and none of
its interpolations (``${oc.env:…}``) is resolved. From the folder only plain strings are taken: the
MLflow experiment name, and the tracking URI it was meant for, which is used only where it is a
local SQLite store or matches ``--tracking-uri``; otherwise ``--tracking-uri`` must say where to
send it (default: the uploader's local store ``<--store-dir>/mlflow.db``, ``outputs/mlflow.db``;
the folder's own ``paths.outputs_dir`` is never used). Only regular files inside the folder are
uploaded (a symbolic link could point anywhere on the uploading machine), and a malformed
``metrics.json`` is refused in one line. A folder that was uploaded remembers its MLflow run id
(``TRACKED.json``) and is skipped the next time.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from acoustlab.core.contracts import declared
from acoustlab.core.errors import AcoustlabError, ConfigError
from acoustlab.reporting.experiment_log import PENDING_FILE, REQUIRED_METRICS_KEYS, load_received_yaml, log_run_dir, read_metrics
from acoustlab.run.registry import CONF_DIR, build

log = logging.getLogger(__name__)
#: The tracking option of this installation that uploads use.
DEFAULT_TRACKING_OPTION = "mlflow"
#: Written into a run directory once it is uploaded (its MLflow run id); a later upload skips it.
TRACKED_FILE = "TRACKED.json"


def _plain_string(value: Any) -> str | None:
    """``value`` when it is a plain string without interpolation, else None."""
    return value if isinstance(value, str) and "${" not in value else None


def tracker_for(run_dir: Path, tracking_uri: str | None, experiment: str | None, store_dir: str = "outputs") -> Any:
    """The uploader's MLflow tracker for ``run_dir``, with only plain strings taken from the folder (module docstring)."""
    config_file = run_dir / "config_resolved.yaml"
    if not config_file.exists():
        raise ConfigError(f"{config_file} is missing: {run_dir} is not an acoustlab run directory")
    received = load_received_yaml(config_file)
    tracking = received.get("tracking") if isinstance(received.get("tracking"), dict) else {}
    node = OmegaConf.load(CONF_DIR / "tracking" / f"{DEFAULT_TRACKING_OPTION}.yaml")
    node.store_dir = store_dir  # the uploader's, never the received folder's paths.outputs_dir
    node.tracking_uri = tracking_uri
    if tracking_uri is None:
        meant_for = _plain_string(tracking.get("tracking_uri"))
        if meant_for and not meant_for.startswith("sqlite:"):
            log.warning(
                "%s was meant for %s; uploading to the local store instead (pass --tracking-uri to send it there)", run_dir, meant_for
            )
    node.experiment_name = experiment or _plain_string(tracking.get("experiment_name")) or node.experiment_name
    return build(node, "tracking")


def main(argv: list[str] | None = None) -> int:
    """``python -m acoustlab.upload RUN_DIR ... [--tracking-uri URI] [--experiment NAME]``."""
    parser = argparse.ArgumentParser(
        prog="python -m acoustlab.upload", description="Upload run directories to MLflow (e.g. after the server was unreachable)."
    )
    parser.add_argument("run_dirs", nargs="+", type=Path, help="run directories (holding metrics.json), or folders searched for them")
    parser.add_argument("--tracking-uri", help="MLflow tracking URI; default: the local store <outputs_dir>/mlflow.db")
    parser.add_argument("--experiment", help="MLflow experiment name; default: the run's own")
    parser.add_argument(
        "--store-dir",
        default="outputs",
        help="folder of the local MLflow store (mlflow.db, artifacts) when no --tracking-uri is given; default: outputs",
    )
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
        print(
            f"acoustlab.upload: error: no run directories (with metrics.json) under {', '.join(map(str, args.run_dirs))}", file=sys.stderr
        )
        return 2
    failed = 0
    for run_dir in run_dirs:
        try:
            read_metrics(run_dir, REQUIRED_METRICS_KEYS)
            tracker = tracker_for(run_dir, args.tracking_uri, args.experiment, args.store_dir)
        except AcoustlabError as exc:
            print(f"acoustlab.upload: error: {exc}", file=sys.stderr)
            return 2
        marker = run_dir / TRACKED_FILE
        if marker.exists() and not (run_dir / PENDING_FILE).exists():
            log.info("%s was uploaded before (MLflow run %s); skipped", run_dir, json.loads(marker.read_text()).get("run_id"))
            continue
        ok = log_run_dir(tracker, run_dir)
        failed += not ok
        if ok and declared(tracker, "last_run_id"):
            marker.write_text(json.dumps({"run_id": tracker.last_run_id, "tracking_uri": str(declared(tracker, "tracking_uri") or "")}))
    log.info("uploaded %d of %d run directories", len(run_dirs) - failed, len(run_dirs))
    return 1 if failed else 0
