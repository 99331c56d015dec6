"""Hydra entry point: ``python -m acoustlab +site=NAME [group=option ...]`` (also the ``acoustlab`` script)."""

from __future__ import annotations

import contextlib
import json
import logging
import shutil
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from acoustlab.core.errors import AcoustlabError
from acoustlab.run.preflight import check_argv, check_output_dirs

log = logging.getLogger("acoustlab")


def _fail(exc: AcoustlabError) -> None:
    print(f"acoustlab: error: {exc}", file=sys.stderr)
    sys.exit(2)


#: Override keys that never distinguish one run from another in a run's name.
_UNNAMED_KEYS = ("paths.", "tracking", "hydra.", "plots", "data.n_jobs", "cache.")


def run_name_of(overrides: list[str]) -> str:
    """A tracker run name from what the job's command line varies: ``forest model=knn features.drop=[solver]``.

    The site comes first, without its key; output paths, tracking and worker settings are left out.
    """
    site = next((o.split("=", 1)[1] for o in overrides if o.lstrip("+~").startswith("site=")), "")
    rest = [o.lstrip("+") for o in overrides if not o.lstrip("+~").startswith(("site=", *_UNNAMED_KEYS))]
    return " ".join([site, *rest]).strip() or "acoustlab"


def record_failure(run_dir: Path, overrides: list[str], error: str) -> None:
    """A sweep job's ``failed.json`` (its overrides and the error's first line), so the sweep's report lists it."""
    from acoustlab.reporting.report import FAILED_FILE

    with contextlib.suppress(OSError):  # the job's own error is what matters; a folder that cannot be written loses only this
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / FAILED_FILE).write_text(json.dumps({"overrides": overrides, "error": (error.splitlines() or [""])[0][:500]}))


def _remove_if_empty(run_dir: Path) -> None:
    """Remove a run directory that holds only Hydra's own files (a run stopped by its preflight leaves no empty folder)."""
    own = {".hydra", f"{HydraConfig.get().job.name}.log"}
    if run_dir.is_dir() and all(p.name in own for p in run_dir.iterdir()):
        shutil.rmtree(run_dir, ignore_errors=True)
        with contextlib.suppress(OSError):  # the day folder too, when this was its only run
            run_dir.parent.rmdir()


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def _hydra_main(cfg: DictConfig) -> None:
    from acoustlab.run.app import run_experiment
    from acoustlab.run.sweep import parent_run_id_for

    hc = HydraConfig.get()
    parent = parent_run_id_for(Path(hc.sweep.dir)) if hc.mode == RunMode.MULTIRUN else None
    try:
        run_experiment(
            cfg, Path(hc.runtime.output_dir), dict(hc.runtime.choices), parent_run_id=parent, run_name=run_name_of(list(hc.overrides.task))
        )
    except AcoustlabError as exc:
        if hc.mode == RunMode.MULTIRUN:  # let Hydra record the failed job and run the others
            log.error("job %s failed: %s", hc.job.num, exc)
            record_failure(Path(hc.runtime.output_dir), list(hc.overrides.task), str(exc))
            raise
        _remove_if_empty(Path(hc.runtime.output_dir))
        _fail(exc)
    except MemoryError as exc:
        if hc.mode == RunMode.MULTIRUN:
            log.error("job %s ran out of memory: %s", hc.job.num, exc)
            record_failure(Path(hc.runtime.output_dir), list(hc.overrides.task), f"ran out of memory: {exc}")
            raise
        _fail(
            AcoustlabError(
                f"ran out of memory ({str(exc)[:120] or 'MemoryError'}); ask for less at once: localize fewer or shorter events "
                "per run (split the events table), or for a season lower protocol.batch_events"
            )
        )
    except Exception as exc:
        if hc.mode == RunMode.MULTIRUN:  # Hydra re-raises only the first failed job's exception: log every one
            log.exception("job %s failed", hc.job.num)
            record_failure(Path(hc.runtime.output_dir), list(hc.overrides.task), f"{type(exc).__name__}: {exc}")
        raise


def main() -> None:
    """Console-script entry point: preflight the command line, then hand over to Hydra.

    ``acoustlab report ...`` and ``acoustlab upload ...`` run the report and upload commands;
    ``acoustlab localize ...`` is the main job with ``protocol=localize`` (positions of recordings);
    ``acoustlab season ...`` is ``protocol=season`` (a season of long recordings from detector tables);
    ``acoustlab calibrate ...`` is ``protocol=calibrate`` (the array from playbacks at known spots).
    """
    if len(sys.argv) > 1 and sys.argv[1] == "localize":  # acoustlab localize +site=NAME field=recordings …
        sys.argv = [sys.argv[0], *sys.argv[2:], "protocol=localize"]  # last: Hydra's flags (-m) may follow the command
    if len(sys.argv) > 1 and sys.argv[1] == "calibrate":  # acoustlab calibrate +site=NAME field=recordings … (playbacks)
        sys.argv = [sys.argv[0], *sys.argv[2:], "protocol=calibrate"]
    if len(sys.argv) > 1 and sys.argv[1] == "season":  # acoustlab season +site=NAME protocol.recordings.audio_dir=… …
        sys.argv = [sys.argv[0], *sys.argv[2:], "protocol=season"]
    if len(sys.argv) > 1 and sys.argv[1] in ("report", "upload"):
        from acoustlab.reporting import report
        from acoustlab.run import upload

        command = sys.argv[1]
        sys.exit((report.main if command == "report" else upload.main)(sys.argv[2:]))
    try:
        check_argv(sys.argv[1:])
        check_output_dirs(sys.argv[1:])
    except AcoustlabError as exc:
        _fail(exc)
    _hydra_main()


if __name__ == "__main__":
    main()
