"""A season's answer does not depend on how the work is cut: 10⁵ detections, three batch/chunk settings, two shard counts.

Usage: python experiments/season_invariance.py [--site frozen_lake] [--detections 100000] [--workdir DIR]

A synthetic season (``acoustlab.season.synthetic``: long files per recorder, a Raven table per
recorder, one selection per call per recorder) with ``--detections`` rows over all tables is
localized by ``python -m acoustlab season`` with its defaults three times, from one fitted method
(the first run fits it; the others find it in their folder and reuse it, as a resumed or sharded
season does):

* ``batch_events=16, chunk_events=256``, one process (the defaults);
* ``batch_events=1, chunk_events=97``, one process;
* ``batch_events=7, chunk_events=1000``, two local shards (``protocol.n_jobs=2``).

Every column of every row of ``positions.parquet`` is compared with the first run's, bit for bit
(NaN equal to NaN). Reported: rows, cells compared, cells that differ, the largest difference, and
each run's wall time and detections per second of wall time. ``--workdir`` keeps the recordings
(about 5 GiB for 10⁵ detections) for a rerun. Writes experiments/results/season_invariance.md.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from common import compose_cfg, machine, time_cli, write_results

from acoustlab.method.saved import DIGEST_FILE, METHOD_FILE
from acoustlab.season.synthetic import SyntheticSeason, write_season
from acoustlab.stages.sites import site_from_config

log = logging.getLogger("experiments.season_invariance")
#: The compared ways to cut the work, the reference first.
SETTINGS = {
    "batch 16, chunk 256, 1 shard": ["protocol.batch_events=16", "protocol.chunk_events=256"],
    "batch 1, chunk 97, 1 shard": ["protocol.batch_events=1", "protocol.chunk_events=97"],
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


def run(site: str, folder: Path, out: Path, extra: list[str]) -> float:
    """One ``python -m acoustlab season`` over the season in ``folder`` into ``out``; its wall time, s."""
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
    return time_cli(args)


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
        rows, reference = {}, None
        for k, (name, extra) in enumerate(SETTINGS.items()):
            out = work / f"out{k}"
            shutil.rmtree(out, ignore_errors=True)
            shutil.rmtree(f"{out}_run", ignore_errors=True)
            if k:  # the method the first run fitted, as a resumed or sharded season finds it
                out.mkdir()
                for file in (METHOD_FILE, DIGEST_FILE):
                    shutil.copy(work / "out0" / file, out / file)
            seconds = run(args.site, work / "season", out, extra)
            table = pd.read_parquet(Path(f"{out}_run") / "positions.parquet")
            reference = table if reference is None else reference
            rows[name] = {"rows": len(table), **differences(table, reference), "wall s": seconds, "detections/s": n_detections / seconds}
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
        "The first run's wall time includes fitting the method; the others reuse it. "
        f"Detections per second are of wall time on this machine: {machine()}.",
    ]
    write_results("season_invariance", {"rows": rows, "n_detections": n_detections}, markdown)


if __name__ == "__main__":
    main()
