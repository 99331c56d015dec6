"""A season localized end to end as a user runs it: detections per second of CPU and peak memory.

A synthetic season (``acoustlab.season.synthetic``: calls rendered into long noise files, one
folder per recorder, a Raven table per recorder) is fitted once per case, then localized with
``python -m acoustlab season protocol.stage=localize`` in its own process. Detections per second
count the CPU time (user + system) of that process above the same command with nothing left to do
(imports and loading the fitted method), so start-up does not flatter or hide the per-detection
cost; the peak is that process' own high-water mark (VmHWM).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from run import REPO

WORK = REPO / "outputs" / "benchmarks" / "season"

#: Runs ``python -m acoustlab ARGS`` and prints the process' own peak RSS (VmHWM, KiB) at exit. ``ru_maxrss`` of
#: ``os.wait4`` cannot serve: Linux carries the forking parent's high-water mark into the child.
PEAK_PROBE = (
    "import atexit, runpy, sys; "
    "atexit.register(lambda: print('PEAK_RSS_KIB', next(l.split()[1] for l in open('/proc/self/status') "
    "if l.startswith('VmHWM')), file=sys.stderr)); sys.argv = ['acoustlab', *sys.argv[1:]]; "
    "runpy.run_module('acoustlab', run_name='__main__')"
)


def season_args(site: str, folder: Path, output_dir: Path, *extra: str) -> list[str]:
    """The ``python -m acoustlab season`` arguments for the synthetic season in ``folder``."""
    return [
        "season",
        f"+site={site}",
        "tracking=none",
        "plots=false",
        f"protocol.recordings.audio_dir={folder / 'audio'}",
        f"protocol.detections.paths=[{folder / 'raven'}]",
        f"protocol.output_dir={output_dir}",
        f"hydra.run.dir={output_dir}_run",
        *extra,
    ]


def measured(args: list[str]) -> dict[str, float]:
    """CPU seconds (user + system, children included) and own peak RSS (MiB) of ``python -m acoustlab ARGS``."""
    proc = subprocess.Popen(
        [sys.executable, "-c", PEAK_PROBE, *args], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    output = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    if status != 0:
        raise RuntimeError(f"failed: python -m acoustlab {' '.join(args)}\n{output[-3000:]}")
    peak = [line.split()[1] for line in output.splitlines() if line.startswith("PEAK_RSS_KIB")]
    return {"cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mib": int(peak[-1]) / 1024}


class Season:
    """Localize a synthetic season with the season's defaults and with the full feature set."""

    params = [["forest"], ["default", "features=physics"], [2000]]
    param_names = ["site", "settings", "calls"]
    quick_params = [["frozen_lake"], ["default"], [60]]

    def setup(self, site: str, settings: str, calls: int) -> None:
        from acoustlab.run.plugin_checks import compose_config
        from acoustlab.season.synthetic import SyntheticSeason, write_season
        from acoustlab.stages.sites import site_from_config

        self.extra = [] if settings == "default" else [settings]
        self.site = site
        self.folder = WORK / f"{site}_{calls}"
        if not (self.folder / "truth.csv").is_file():
            cfg = compose_config([f"+site={site}"])
            season = SyntheticSeason.for_site(
                site_from_config(cfg.site),
                duration_s=2.2 * calls + 5,
                file_s=600.0,
                n_calls=calls,
                min_spacing_s=2.0,
                sample_rate_hz=float(cfg.simulator.sample_rate_hz),
                seed=calls,
            )
            shutil.rmtree(self.folder, ignore_errors=True)
            write_season(season, self.folder).to_csv(self.folder / "truth.csv", index=False)
        from acoustlab.method.saved import METHOD_FILE

        self.fitted = self.folder / f"fitted_{settings.replace('=', '_')}"
        if not (self.fitted / METHOD_FILE).is_file():  # none yet, or one saved in another format: fit (again)
            measured(season_args(site, self.folder, self.fitted, "protocol.stage=fit", *self.extra))

    def _localize(self) -> tuple[int, dict[str, float], dict[str, float]]:
        """Localize into a fresh folder holding the fitted method; the run, and the same command with nothing left to do."""
        from acoustlab.method.saved import DIGEST_FILE, METHOD_FILE
        from acoustlab.season.stream import EVENTS

        out = self.folder / "localized"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir()
        for name in (METHOD_FILE, DIGEST_FILE):
            shutil.copy2(self.fitted / name, out / name)
        measured(season_args(self.site, self.folder, out, "protocol.stage=fit", *self.extra))  # tables; the method is reused
        run = measured(season_args(self.site, self.folder, out, "protocol.stage=localize", *self.extra))
        idle = measured(season_args(self.site, self.folder, out, "protocol.stage=localize", *self.extra))
        import pandas as pd

        return len(pd.read_parquet(out / EVENTS)), run, idle

    def track_detections_per_s(self, site: str, settings: str, calls: int) -> float:
        n_events, run, idle = self._localize()
        self.peak_mib = run["peak_rss_mib"] - idle["peak_rss_mib"]
        return n_events / max(run["cpu_s"] - idle["cpu_s"], 1e-9)

    track_detections_per_s.unit = "detections/s of CPU"

    def track_peak_above_idle_mib(self, site: str, settings: str, calls: int) -> float:
        if not hasattr(self, "peak_mib"):
            self.track_detections_per_s(site, settings, calls)
        return self.peak_mib

    track_peak_above_idle_mib.unit = "MiB"


class FilesFingerprint:
    """The check a season's every localize stage makes of its audio files: ``os.stat`` alone, and with each file's
    sampled content digest (``sampled_file_sha256``), over 10⁴ files of 256 KiB (from the page cache once warm)."""

    params = [[10_000]]
    param_names = ["n_files"]

    def setup(self, n_files: int) -> None:
        self.folder = WORK / "fingerprint"
        self.folder.mkdir(parents=True, exist_ok=True)
        blob = os.urandom(256 * 1024)
        self.paths = [self.folder / f"file{k:05d}.wav" for k in range(n_files)]
        for path in self.paths:
            if not path.is_file():
                path.write_bytes(blob)

    def teardown(self, n_files: int) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)

    def time_stat(self, n_files: int) -> None:
        for path in self.paths:
            os.stat(path)

    def time_stat_and_sampled_digest(self, n_files: int) -> None:
        from acoustlab.core.digests import sampled_file_sha256

        for path in self.paths:
            os.stat(path)
            sampled_file_sha256(path)


class EventGrouping:
    """Detections grouped into events (``group_detections``): 10⁶ rows, 5 recorders hearing each call, and every
    detection repeated ``repeats`` times (a table read twice, a detector writing a window per view)."""

    params = [[1_000_000], [1, 4]]
    param_names = ["n_rows", "repeats"]

    def setup(self, n_rows: int, repeats: int) -> None:
        import numpy as np
        import pandas as pd

        from acoustlab.core import columns as col

        rng = np.random.default_rng(0)
        calls = n_rows // (5 * repeats)
        start = np.repeat(np.sort(rng.uniform(0, 30 * 86400, calls)), 5) + rng.uniform(0, 0.05, 5 * calls)
        self.detections = pd.DataFrame(
            {
                "recorder_id": pd.Categorical(np.tile([f"R{k}" for k in range(5)], calls).repeat(repeats)),
                col.START: start.repeat(repeats),
                col.END: start.repeat(repeats) + 1.0,
                "low_hz": 2000.0,
                "high_hz": 6000.0,
                "label": pd.Categorical(np.full(5 * calls * repeats, "song")),
                "score": 0.9,
                "source": "t.txt:2",
            }
        )

    def time_group(self, n_rows: int, repeats: int) -> None:
        from acoustlab.season.events import group_detections

        group_detections(self.detections, 0.2)
