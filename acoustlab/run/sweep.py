"""Sweeps (Hydra multirun): one parent run in the tracker with the jobs as children, and a report.

``SweepTrackingCallback`` is registered in ``conf/config.yaml`` under ``hydra.callbacks``. Before
the jobs start it opens the parent run and writes its id to ``<sweep dir>/.acoustlab_sweep.json``;
each job (in this process, a joblib worker or a SLURM node: the sweep dir is on the shared file
system) reads that file and logs its run as a child. After the jobs it writes the sweep's report
(``<sweep dir>/report/``) and attaches it and the summary tables to the parent run.
"""

from __future__ import annotations

import atexit
import contextlib
import itertools
import json
import logging
import signal
import sys
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

log = logging.getLogger(__name__)

#: File in the sweep dir that tells jobs their parent run.
SWEEP_FILE = ".acoustlab_sweep.json"


def parent_run_id_for(sweep_dir: Path) -> str | None:
    """The parent run id a sweep's jobs log under (None when the sweep has none)."""
    path = Path(sweep_dir) / SWEEP_FILE
    if not path.exists():
        return None
    return json.loads(path.read_text()).get("parent_run_id")


def sweep_jobs(config: DictConfig) -> list[list[str]]:
    """The override list of every job of a sweep, in launch order (as Hydra's basic sweeper expands
    ``hydra.sweeper.params`` followed by the command line's overrides)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    params = config.hydra.sweeper.get("params") or {}
    texts = [f"{k}={v}" for k, v in params.items()] + [str(o) for o in config.hydra.overrides.task]
    choices: dict[str, list[str]] = {}
    for override in OverridesParser.create().parse_overrides(texts):
        key = override.get_key_element()
        # a key set on the command line replaces the same key of hydra.sweeper.params (as Hydra's sweeper does)
        if override.is_sweep_override():
            choices[key] = [f"{key}={value}" for value in override.sweep_string_iterator()]
        else:
            choices[key] = [f"{key}={override.get_value_element_as_str()}"]
    return [list(job) for job in itertools.product(*choices.values())]


def preflight_jobs(jobs: list[list[str]]) -> list[str]:
    """Build and check every job's config (``acoustlab.run.app.build_run``) without running it.

    Returns
    -------
    list of str
        One message per job that would fail (its overrides and the reason); empty when all pass.
    """
    from hydra import compose
    from hydra.errors import ConfigCompositionException

    from acoustlab.core.errors import AcoustlabError
    from acoustlab.run.app import build_run

    problems = []
    for number, job in enumerate(jobs):
        try:
            build_run(compose(config_name="config", overrides=job))
        except AcoustlabError as exc:
            problems.append(f"job #{number} ({' '.join(job)}): {exc}")
        except ConfigCompositionException as exc:  # a mistyped key or value, caught by the typed schema
            reason = str(exc.__cause__).splitlines()[0] if exc.__cause__ else ""
            problems.append(f"job #{number} ({' '.join(job)}): {exc}" + (f": {reason}" if reason else ""))
        except Exception as exc:  # noqa: BLE001 - a check we cannot run must not block the sweep
            log.warning("preflight could not check job #%d (%s): %s: %s", number, " ".join(job), type(exc).__name__, exc)
    return problems


class SweepTrackingCallback(Callback):
    """Checks every job, opens a parent tracker run per sweep, writes the report, closes the parent run.

    Parameters
    ----------
    report : bool
        Write ``report/report.md`` and ``report/report.html`` into the sweep dir when the sweep ends.
    preflight : bool
        Build and check every job's config before the first job starts (missing TabPFN weights, a
        mistyped value, a bad site file…) and stop the sweep with one line per failing job, so a
        cluster array fails in seconds instead of after its queue wait.
    """

    def __init__(self, report: bool = True, preflight: bool = True) -> None:
        self.report = report
        self.preflight = preflight
        self._open: tuple[DictConfig, Path] | None = None
        self._stopped = False

    @staticmethod
    def _tracker(config: DictConfig) -> Any:
        from acoustlab.run.registry import build

        return build(config.tracking, "tracking")

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Preflight every job, then open the parent run (a tracker failure only costs the grouping)."""
        from acoustlab.reporting.run_files import code_version

        if self.preflight:
            jobs = sweep_jobs(config)
            problems = preflight_jobs(jobs)
            if problems:
                for line in problems:
                    print(f"acoustlab: error: {line}", file=sys.stderr)
                print(
                    f"acoustlab: {len(problems)} of {len(jobs)} sweep jobs would fail; nothing was run "
                    "(hydra.callbacks.sweep_tracking.preflight=false runs the others anyway)",
                    file=sys.stderr,
                )
                sys.exit(2)
            log.info("preflight: all %d jobs of the sweep check out", len(jobs))
        if config.get("expected_duration"):
            log.info("this sweep's experiment takes %s", config.expected_duration)
        sweep_dir = Path(str(config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)
        overrides = [str(o) for o in config.hydra.overrides.task]
        run_id = destination = None
        try:
            tracker = self._tracker(config)
            destination = getattr(tracker, "destination", None)
            run_id = tracker.open_sweep(
                f"sweep-{sweep_dir.parent.name}-{sweep_dir.name}",
                {"sweep.overrides": " ".join(overrides), "sweep.dir": str(sweep_dir.resolve())},
                {"acoustlab.sweep": "parent", "code_version": code_version(), "sweep_dir": str(sweep_dir.resolve())},
            )
        except Exception as exc:  # noqa: BLE001 - jobs still run and keep their results
            log.warning("could not open the sweep's parent run (%s: %s); jobs are logged as separate runs", type(exc).__name__, exc)
        (sweep_dir / SWEEP_FILE).write_text(
            json.dumps({"parent_run_id": run_id, "destination": destination, "overrides": overrides}, indent=2)
        )
        # Hydra skips on_multirun_end when a job failed: report what finished and mark the parent FAILED at exit.
        self._open = (config, sweep_dir)
        atexit.register(self._close_after_failure)
        for signum in (signal.SIGINT, signal.SIGTERM):  # Ctrl-C, scancel, kill: the parent is closed KILLED, not left RUNNING
            with contextlib.suppress(ValueError):  # only the main thread may set handlers
                signal.signal(signum, self._on_stop_signal)

    def _on_stop_signal(self, signum: int, frame: Any) -> None:
        """A stop request: remember it (the parent run is then closed KILLED at exit) and stop as Python would."""
        self._stopped = True
        signal.signal(signum, signal.SIG_DFL)
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise SystemExit(128 + signum)

    def _close_after_failure(self) -> None:
        if self._open is not None:
            config, _ = self._open
            status = "KILLED" if self._stopped else "FAILED"
            log.warning(
                "the sweep %s: reporting the finished jobs and marking the parent run %s",
                "was stopped" if self._stopped else "ended with failed jobs",
                status,
            )
            self._finish(config, status)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Write the report and close the parent run with the sweep's summary tables."""
        self._finish(config, "FINISHED")

    def _finish(self, config: DictConfig, status: str) -> None:
        self._open = None
        sweep_dir = Path(str(config.hydra.sweep.dir))
        run_id = parent_run_id_for(sweep_dir)
        report_dir = None
        tables = {}
        try:
            from acoustlab.reporting.report import collect_failed, collect_runs, error_rows, write_report

            runs, failed = collect_runs([sweep_dir]), collect_failed([sweep_dir])
            if runs:
                tables["tables/sweep_errors.json"] = error_rows(runs)
            if (runs or failed) and self.report:
                report_dir = write_report(runs, sweep_dir / "report", failed=failed).parent
        except Exception as exc:  # noqa: BLE001 - the runs themselves are already written
            log.warning("could not write the sweep report (%s: %s); run python -m acoustlab.report %s", type(exc).__name__, exc, sweep_dir)
        if run_id is None:
            return
        try:
            self._tracker(config).close_sweep(run_id, status, tables, [str(report_dir)] if report_dir else [])
        except Exception as exc:  # noqa: BLE001
            log.warning("could not close the sweep's parent run %s (%s: %s)", run_id, type(exc).__name__, exc)
