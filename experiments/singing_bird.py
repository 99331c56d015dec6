"""A bird singing every few seconds all season, through a window classifier's tables: is every song placed?

Usage: python experiments/singing_bird.py [--site forest] [--minutes 10] [--spacing-s 2.5] [--seed 0]

A synthetic season (``acoustlab.season.synthetic``: long files per recorder, files cut every 2
minutes so songs cross file boundaries) of one bird on one perch inside the array, singing a
0.15–0.4 s song every ``--spacing-s`` seconds (plus up to 0.2 s of jitter) for ``--minutes``. Three
detector tables of the same recordings go through ``python -m acoustlab season`` with its defaults:

* ``raven``: one selection per song per recorder (its exact bounds), the reference;
* ``birdnet``: BirdNET-Analyzer's fixed 3-s windows (step 3 s) wherever a song touches one, so a
  singing bird is a chain of consecutive windows on every recorder;
* ``birdnet_overlap``: 3-s windows every 1.5 s (BirdNET's ``--overlap 1.5``).

A song counts as placed when a placed event's window holds its arrival at the nearest recorder and
the event's position is within 5 m of the perch. Reported per table: songs, events, songs placed,
and the placed events' error (median, share > 5 m). Writes experiments/results/singing_bird.md.
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
from acoustlab.season.synthetic import SyntheticSeason, write_season, write_window_tables
from acoustlab.stages.sites import site_from_config

log = logging.getLogger("experiments.singing_bird")
#: A song is placed when an event holding it is within this distance of the perch, m.
PLACED_WITHIN_M = 5.0
TABLES = {
    "raven": ("raven", "raven"),
    "birdnet": ("birdnet", "birdnet"),
    "birdnet_overlap": ("birdnet_overlap", "birdnet"),
}


def season(site: str, folder: Path, tables: str, fmt: str, out: Path) -> pd.DataFrame:
    """The positions of one season run (its defaults) over the detector tables in ``folder/tables``."""
    args = [
        "season",
        f"+site={site}",
        "tracking=none",
        "plots=false",
        f"protocol.recordings.audio_dir={folder / 'audio'}",
        f"protocol.detections.paths=[{folder / tables}]",
        f"protocol.detections.format={fmt}",
        f"protocol.output_dir={out}",
        f"hydra.run.dir={out}_run",
    ]
    time_cli(args)
    return pd.read_parquet(Path(f"{out}_run") / "positions.parquet")


def score(positions: pd.DataFrame, truth: pd.DataFrame, mics: np.ndarray, speed_m_s: float) -> dict[str, float]:
    """Songs placed (a placed event holding the song's first arrival, within ``PLACED_WITHIN_M`` of the perch) and the events' error."""
    perch = truth[["x_m", "y_m", "z_m"]].to_numpy(float)[0]
    first_arrival = truth["emission_s"].to_numpy(float) + np.linalg.norm(mics - perch, axis=1).min() / speed_m_s
    placed = positions[positions["placed"].to_numpy(bool)]
    error = np.hypot(placed["x_m"].to_numpy(float) - perch[0], placed["y_m"].to_numpy(float) - perch[1])
    close = error <= PLACED_WITHIN_M
    start, end = placed["start_s"].to_numpy(float), placed["end_s"].to_numpy(float)
    held = (start[None, close] <= first_arrival[:, None]) & (first_arrival[:, None] <= end[None, close])
    return {
        "songs": len(truth),
        "events": len(positions),
        "events placed": len(placed),
        "songs placed (%)": 100.0 * held.any(axis=1).mean(),
        "events per song": len(positions) / len(truth),
        "placed p50 error (m)": float(np.median(error)) if error.size else float("nan"),
        "placed > 5 m (%)": 100.0 * float((~close).mean()) if error.size else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", default="forest")
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--spacing-s", type=float, default=2.5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = compose_cfg([f"+site={args.site}"])
    site = site_from_config(cfg.site)
    mics = site.mic_positions_m
    perch = (*(mics[:, :2].mean(axis=0) + [3.0, -2.0]), float(np.mean(site.source_height_range_m)))
    duration = 60.0 * args.minutes
    settings = SyntheticSeason.for_site(
        site,
        duration_s=duration,
        file_s=120.0,
        n_calls=int((duration - 2) / args.spacing_s),
        min_spacing_s=args.spacing_s,
        sample_rate_hz=float(cfg.simulator.sample_rate_hz),
        seed=args.seed,
        singer_m=perch,
    )
    rows, seconds = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        truth = write_season(settings, folder)
        write_window_tables(settings, truth, folder)
        (folder / "birdnet").rename(folder / "birdnet_fixed")
        write_window_tables(settings, truth, folder, step_s=1.5)
        (folder / "birdnet").rename(folder / "birdnet_overlap")
        (folder / "birdnet_fixed").rename(folder / "birdnet")
        for k, (name, (tables, fmt)) in enumerate(TABLES.items()):
            if k:  # the same config: the method fitted by the first run is reused (the season's own reuse), not refitted
                (folder / f"out_{name}").mkdir()
                for file in (METHOD_FILE, DIGEST_FILE):
                    shutil.copy(folder / f"out_{next(iter(TABLES))}" / file, folder / f"out_{name}" / file)
            started = time.perf_counter()
            positions = season(args.site, folder, tables, fmt, folder / f"out_{name}")
            seconds[name] = time.perf_counter() - started
            rows[name] = score(positions, truth, mics, settings.speed_of_sound_m_s)
            log.info("%s: %s (%.0f s)", name, rows[name], seconds[name])
    table = pd.DataFrame(rows).T
    markdown = [
        "# A bird singing every few seconds, through a window classifier's tables",
        "",
        f"`python experiments/singing_bird.py --site {args.site} --minutes {args.minutes:g} --spacing-s {args.spacing_s:g} "
        f"--seed {args.seed}`: one bird at ({perch[0]:.1f}, {perch[1]:.1f}, {perch[2]:.1f}) m singing every "
        f"{args.spacing_s:g} s (+ up to 0.2 s) for {args.minutes:g} min, {len(truth)} songs; `season` with its defaults "
        f"over three detector tables of the same recordings. A song is placed when a placed event holds its first arrival "
        f"and lies within {PLACED_WITHIN_M:g} m of the perch.",
        "",
        table.to_markdown(floatfmt=".3g"),
        "",
        "Wall time per season run (the first fits the method, the others reuse it): "
        + ", ".join(f"{name} {s:.0f} s" for name, s in seconds.items())
        + f". Machine: {machine()}.",
    ]
    write_results("singing_bird", {"rows": rows, "seconds": seconds}, markdown)


if __name__ == "__main__":
    main()
