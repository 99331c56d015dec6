"""A season's answer and memory do not depend on how the work is cut: 10⁵ detections, three batch/chunk settings, two shard counts.

Usage: python experiments/season_invariance.py [--site frozen_lake] [--detections 100000] [--workdir DIR]

A synthetic season (``acoustlab.season.synthetic``: long files per recorder, a Raven table per
recorder, one selection per call per recorder) with ``--detections`` rows over all tables is
localized by ``python -m acoustlab season`` with its defaults three times, from one fitted method
(the first run fits it; the others find it in their folder and reuse it, as a resumed or sharded
season does):

* ``batch_events=16, chunk_events=256``, one process (the defaults);
* ``batch_events=16, chunk_events=7``, two local shards (``protocol.n_jobs=2``): many small parts;
* ``batch_events=7, chunk_events=1000``, two local shards.

Every column of every row of ``positions.parquet`` is compared with the first run's, bit for bit
(NaN equal to NaN). Reported: rows, cells compared, cells that differ, the largest difference,
whether every call of the season is one row (each call's event id once, none missing), each
run's peak resident memory (the largest of the command and its workers, ``wait4`` from a small
intermediate process), wall time
and detections per second of wall time. ``--workdir`` keeps the recordings
(about 5 GiB for 10⁵ detections) for a rerun. Writes experiments/results/season_invariance.md.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from common import REPO, compose_cfg, machine, write_results

from acoustlab.method.saved import DIGEST_FILE, METHOD_FILE
from acoustlab.season.synthetic import SyntheticSeason, write_season
from acoustlab.stages.sites import site_from_config

log = logging.getLogger("experiments.season_invariance")
#: The compared ways to cut the work, the reference first.
SETTINGS = {
    "batch 16, chunk 256, 1 shard": ["protocol.batch_events=16", "protocol.chunk_events=256"],
    "batch 16, chunk 7, 2 shards": ["protocol.batch_events=16", "protocol.chunk_events=7", "protocol.n_jobs=2"],
    "batch 7, chunk 1000, 2 shards": ["protocol.batch_events=7", "protocol.chunk_events=1000", "protocol.n_jobs=2"],
}


def recordings(site_name: str, n_detections: int, folder: Path) -> int:
    """Write (or find) the synthetic season in ``folder``; the number of detections in its tables."""
    cfg = compose_cfg([f"+site={site_name}"])
    site = site_from_config(cfg.site)
    n_calls = int(np.ceil(n_detections / site.n_mics))
    if not (folder / "truth.csv").is_file():
        settings = SyntheticSeason.for_site(
            site,
            duration_s=1.1 * n_calls + 5,
            file_s=600.0,
            n_calls=n_calls,
            min_spacing_s=1.0,
            sample_rate_hz=float(cfg.simulator.sample_rate_hz),
            seed=0,
        )
        started = time.perf_counter()
        write_season(settings, folder).to_csv(folder / "truth.csv", index=False)
        log.info("wrote %d calls × %d recorders in %.0f s", n_calls, site.n_mics, time.perf_counter() - started)
    return sum(len(pd.read_csv(t, sep="\t")) for t in sorted((folder / "raven").glob("*.txt")))


def run(site: str, folder: Path, out: Path, extra: list[str]) -> tuple[float, float]:
    """One ``python -m acoustlab season`` over the season in ``folder`` into ``out``; its wall time, s, and peak memory, MiB."""
    args = [
        "season",
        f"+site={site}",
        "tracking=none",
        "plots=false",
        "protocol.write_csv=false",
        f"protocol.recordings.audio_dir={folder / 'audio'}",
        f"protocol.detections.paths=[{folder / 'raven'}]",
        f"protocol.output_dir={out}",
        f"hydra.run.dir={out}_run",
        *extra,
    ]
    return time_cli_with_memory(args)


#: Runs its arguments as a command and prints the command's peak resident memory (kB on Linux). A command forked straight
#: from this experiment would inherit the experiment's own high-water mark (Linux carries it across fork and exec), so
#: it is forked from this small process instead. benchmarks/bench_season.py's PEAK_PROBE reads the command's own VmHWM,
#: which leaves out its workers; here the largest of the command and the workers it waited for is wanted (two shards).
_PEAK_OF = (
    "import os, subprocess, sys; p = subprocess.Popen(sys.argv[1:]); _, status, usage = os.wait4(p.pid, 0); "
    "print(usage.ru_maxrss, file=sys.stderr); sys.exit(os.waitstatus_to_exitcode(status))"
)


def time_cli_with_memory(args: list[str]) -> tuple[float, float]:
    """Seconds and peak resident MiB of one ``python -m acoustlab ARGS`` (the largest of it and the workers it waited for)."""
    started = time.perf_counter()
    command = [sys.executable, "-c", _PEAK_OF, sys.executable, "-m", "acoustlab", *args]
    proc = subprocess.run(command, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    elapsed = time.perf_counter() - started
    if proc.returncode != 0:
        raise SystemExit(f"command failed: {args}\n{proc.stderr[-3000:]}")
    peak_mib = int(proc.stderr.strip().splitlines()[-1]) / 1024  # Linux reports kilobytes
    log.info("%6.1f s, %6.0f MiB  %s", elapsed, peak_mib, " ".join(args))
    return elapsed, peak_mib


def every_call_once(table: pd.DataFrame, n_calls: int) -> bool:
    """Whether the positions hold one row per call of the season: ``n_calls`` rows, each event id once."""
    ids = table["event_id"]
    return len(table) == n_calls and ids.is_unique and ids.notna().all()


def differences(table: pd.DataFrame, reference: pd.DataFrame) -> dict[str, float]:
    """Cells of ``table`` that are not bit for bit ``reference``'s (NaN equal to NaN), and the largest numeric difference."""
    if list(table.columns) != list(reference.columns) or len(table) != len(reference):
        return {"cells": float("nan"), "differing cells": float("nan"), "largest difference": float("nan")}
    differing, largest = 0, 0.0
    for name in reference.columns:
        a, b = table[name].to_numpy(), reference[name].to_numpy()
        if a.dtype.kind == "f" and a.dtype == b.dtype:
            same = (a.view(f"u{a.itemsize}") == b.view(f"u{b.itemsize}")) | (np.isnan(a) & np.isnan(b))
            finite = np.isfinite(a) & np.isfinite(b)
            largest = max(largest, float(np.abs(a[finite] - b[finite]).max(initial=0.0)))
        else:
            same = pd.Series(a).astype(str).to_numpy() == pd.Series(b).astype(str).to_numpy()
        differing += int((~same).sum())
    return {"cells": float(reference.size), "differing cells": float(differing), "largest difference": largest}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", default="frozen_lake")
    parser.add_argument("--detections", type=int, default=100_000)
    parser.add_argument("--workdir", type=Path, default=None, help="keep the recordings here (default: a temporary folder)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        n_detections = recordings(args.site, args.detections, work / "season")
        n_calls = len(pd.read_csv(work / "season" / "truth.csv"))
        rows, reference = {}, None
        for k, (name, extra) in enumerate(SETTINGS.items()):
            out = work / f"out{k}"
            shutil.rmtree(out, ignore_errors=True)
            shutil.rmtree(f"{out}_run", ignore_errors=True)
            if k:  # the method the first run fitted, as a resumed or sharded season finds it
                out.mkdir()
                for file in (METHOD_FILE, DIGEST_FILE):
                    shutil.copy(work / "out0" / file, out / file)
            seconds, peak_mib = run(args.site, work / "season", out, extra)
            table = pd.read_parquet(Path(f"{out}_run") / "positions.parquet")
            reference = table if reference is None else reference
            rows[name] = {
                "rows": len(table),
                **differences(table, reference),
                "every call once": every_call_once(table, n_calls),
                "peak MiB": peak_mib,
                "wall s": seconds,
                "detections/s": n_detections / seconds,
            }
            log.info("%s: %s", name, rows[name])
    frame = pd.DataFrame(rows).T
    markdown = [
        "# A season's answer does not depend on how the work is cut",
        "",
        f"`python experiments/season_invariance.py --site {args.site} --detections {args.detections}`: a synthetic "
        f"{args.site} season of {n_detections:,} detections (Raven tables, one selection per call per recorder) localized by "
        "`season` with its defaults three ways from one fitted method; every column of every row of `positions.parquet` "
        "compared bit for bit with the first (NaN equal to NaN).",
        "",
        frame.to_markdown(floatfmt=".4g"),
        "",
        "`every call once`: one row per call of the season, each event id once. `peak MiB`: the largest resident memory of "
        "the command or one of its workers. The first run's wall time includes fitting the method; the others reuse it. "
        f"Detections per second are of wall time on this machine: {machine()}.",
    ]
    write_results("season_invariance", {"rows": rows, "n_detections": n_detections}, markdown)


if __name__ == "__main__":
    main()
