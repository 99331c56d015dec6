"""MLflow tracker: one MLflow run per job, in an embedded SQLite store by default."""

from __future__ import annotations

import logging
import os
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import pandas as pd

log = logging.getLogger(__name__)

#: MLflow refuses parameter values longer than this many characters.
_MAX_PARAM_CHARS = 6000


class MlflowTracker:
    """Logs params, metrics, tables and artifacts of a run to MLflow.

    Parameters
    ----------
    experiment_name : str
        MLflow experiment to log into (created if missing).
    tracking_uri : str, optional
        Tracking URI (``http://host:5000`` for a server); None means the SQLite store
        ``<store_dir>/mlflow.db``.
    store_dir : str
        Directory of the default SQLite store (usually ``outputs/``).
    """

    def __init__(self, experiment_name: str = "acoustlab", tracking_uri: str | None = None, store_dir: str = "outputs") -> None:
        self.experiment_name = experiment_name
        self.store_dir = store_dir
        self.tracking_uri = tracking_uri or f"sqlite:///{Path(store_dir).resolve() / 'mlflow.db'}"
        self._run = None
        if self.tracking_uri.startswith(("http://", "https://")):
            # MLflow's defaults retry a dead server for minutes (7 retries, exponential back-off);
            # a run that already kept its results should warn sooner. The user's own settings win.
            os.environ.setdefault("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "3")
            os.environ.setdefault("MLFLOW_HTTP_REQUEST_TIMEOUT", "30")

    @property
    def destination(self) -> str:
        """The tracking URI runs are logged to."""
        return self.tracking_uri

    def check_reachable(self, timeout_s: float = 5.0) -> None:
        """For an ``http(s)://`` server, GET its ``/health`` endpoint; raise ConnectionError if it does not answer.

        MLflow's own client retries an unreachable server for minutes; this probe fails in seconds.
        """
        if not self.tracking_uri.startswith(("http://", "https://")):
            return
        url = self.tracking_uri.rstrip("/") + "/health"
        try:
            with urllib.request.urlopen(url, timeout=timeout_s) as response:  # noqa: S310 - the user's own tracking URI
                if response.status != 200:
                    raise ConnectionError(f"MLflow server {self.tracking_uri} answered {response.status} on /health")
        except (urllib.error.URLError, OSError) as exc:
            raise ConnectionError(f"MLflow server {self.tracking_uri} cannot be reached ({exc})") from None

    def _connect(self) -> None:
        import mlflow

        mlflow.set_tracking_uri(self.tracking_uri)
        if self.tracking_uri.startswith("sqlite:///"):
            store = Path(self.tracking_uri[len("sqlite:///") :])
            store.parent.mkdir(parents=True, exist_ok=True)
            # artifacts beside the store (outputs/mlartifacts), not in ./mlruns of whatever directory the run started in
            if mlflow.get_experiment_by_name(self.experiment_name) is None:
                mlflow.create_experiment(self.experiment_name, artifact_location=(store.parent / "mlartifacts").resolve().as_uri())
        mlflow.set_experiment(self.experiment_name)

    def start(
        self,
        run_name: str,
        params: dict[str, Any],
        tags: dict[str, str],
        parent_run_id: str | None = None,
        start_time_ms: int | None = None,
    ) -> None:
        """Open the run (a child of ``parent_run_id`` when given) and log params and tags.

        Parameter values longer than MLflow allows are truncated. Without ``parent_run_id`` the
        environment variable ``ACOUSTLAB_PARENT_RUN_ID`` is used when set. With ``start_time_ms``
        the run starts when the job did, so MLflow shows the job's duration, not the upload's.
        """
        import mlflow

        self._connect()
        parent = parent_run_id or os.environ.get("ACOUSTLAB_PARENT_RUN_ID") or None
        if start_time_ms is None:
            self._run = mlflow.start_run(run_name=run_name, tags=tags, parent_run_id=parent)
        else:
            client = mlflow.MlflowClient(self.tracking_uri)
            experiment = client.get_experiment_by_name(self.experiment_name)
            created = client.create_run(
                experiment.experiment_id,
                start_time=int(start_time_ms),
                run_name=run_name,
                tags={**tags, **({"mlflow.parentRunId": parent} if parent else {})},
            )
            self._run = mlflow.start_run(run_id=created.info.run_id)
        mlflow.log_params(_clean_params(params))
        log.info(
            "MLflow run %s in %s (experiment %r%s)",
            self._run.info.run_id,
            self.tracking_uri,
            self.experiment_name,
            f", child of {parent}" if parent else "",
        )

    @property
    def run_id(self) -> str | None:
        """The active run's id, once started."""
        return None if self._run is None else self._run.info.run_id

    def log_metrics(self, metrics: dict[str, float]) -> None:
        """Log scalar metrics (names may contain '/', '.', '_')."""
        import mlflow

        mlflow.log_metrics({k: float(v) for k, v in metrics.items()})

    def log_table(self, table: pd.DataFrame, artifact_file: str) -> None:
        """Log a table with ``mlflow.log_table`` (shown in the MLflow UI's evaluation view)."""
        import mlflow

        mlflow.log_table(data=table, artifact_file=artifact_file)

    def log_artifact(self, path: str, artifact_path: str | None = None) -> None:
        """Upload one file as an artifact, under ``artifact_path`` (None: the artifacts' root)."""
        import mlflow

        mlflow.log_artifact(path, artifact_path=artifact_path)

    def finish(self, status: str = "FINISHED", end_time_ms: int | None = None) -> None:
        """Close the run with ``status`` (FINISHED, FAILED or KILLED), at ``end_time_ms`` when given (else now)."""
        import mlflow

        if self._run is not None:
            run_id = self._run.info.run_id
            mlflow.end_run(status=status)
            if end_time_ms is not None:
                mlflow.MlflowClient(self.tracking_uri).set_terminated(run_id, status, end_time=int(end_time_ms))
            self.last_run_id = run_id
            self._run = None

    def open_sweep(self, run_name: str, params: dict[str, Any], tags: dict[str, str]) -> str:
        """Create a sweep's parent run without making it active (jobs may run in this process)."""
        import mlflow

        self.check_reachable()
        self._connect()
        client = mlflow.MlflowClient(self.tracking_uri)
        experiment = client.get_experiment_by_name(self.experiment_name)
        run = client.create_run(experiment.experiment_id, run_name=run_name, tags=tags)
        for key, value in _clean_params(params).items():
            client.log_param(run.info.run_id, key, value)
        log.info("MLflow parent run %s for the sweep in %s", run.info.run_id, self.tracking_uri)
        return run.info.run_id

    def close_sweep(self, run_id: str, status: str, tables: dict[str, pd.DataFrame], artifact_dirs: list[str]) -> None:
        """Log summary tables and directories (e.g. the sweep report) into the parent run and end it."""
        import mlflow

        client = mlflow.MlflowClient(self.tracking_uri)
        for artifact_file, table in tables.items():
            client.log_table(run_id, data=table, artifact_file=artifact_file)
        for directory in artifact_dirs:
            client.log_artifacts(run_id, directory, artifact_path=Path(directory).name)
        client.set_terminated(run_id, status=status)


def _clean_params(params: dict[str, Any]) -> dict[str, str]:
    return {k[:250]: str(v)[:_MAX_PARAM_CHARS] for k, v in params.items()}
