"""A season's peak memory above the floor a localizing process cannot go below, measured on the real code path.

Usage::

    python benchmarks/bench_season_memory.py [--site frozen_lake] [--calls 10000] [--floor-calls 4]

``bench_season.py`` reports a localize's peak RSS above its baseline, the same command once every
chunk is done: the interpreter, the imports and the fitted method, but not the compiled kernels
(numba, the compiled solver, the coarse GCC search), which a process loads only when it first
computes. Those are code, a fixed cost per process whatever the season's size, not data. This
script measures the floor with them, by localizing a season of ``--floor-calls`` calls (a few
events, one batch) with the same fitted method in a fresh process: everything a localizing
process holds except the chunk's data. One run, one machine:

1. renders a season of ``--calls`` calls and one of ``--floor-calls`` calls (``bench_season.py``'s
   settings), fits the method on the first (``protocol.stage=fit``) and gives the second a copy
   (verified by its SHA-256, as a shard does);
2. localizes the season (one process), runs the same command again with nothing left to do (the
   baseline) and localizes the small season (the floor);
3. reports each process' own peak RSS (VmHWM), the season's peak above the baseline and above the
   floor, and both against one chunk's audio (what holding a chunk's clips would take, as in
   ``bench_season.py``).

Writes benchmarks/results/season_memory_<site>.{json,md}.
"""

from __future__ import annotations

import argparse
import logging
import shutil
from pathlib import Path

import pandas as pd
from bench_season import WORK, measured, season_command
from common import compose_cfg, machine, write_results

from acoustlab.method.saved import DIGEST_FILE, METHOD_FILE
from acoustlab.season.stream import EVENTS, read_manifest
from acoustlab.season.synthetic import SyntheticSeason, write_season
from acoustlab.stages.sites import site_from_config

log = logging.getLogger("bench_season_memory")


def render(site, cfg, n_calls: int, file_s: float, folder: Path) -> None:
    """A synthetic season of ``n_calls`` calls in ``folder`` (``bench_season.py``'s settings and seed)."""
    settings = SyntheticSeason.for_site(site, duration_s=2.2 * n_calls + 5, file_s=file_s, n_calls=n_calls, min_spacing_s=2.0,
                                        sample_rate_hz=float(cfg.simulator.sample_rate_hz), seed=n_calls)
    if folder.exists():
        shutil.rmtree(folder)
    write_season(settings, folder)


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--site", default="frozen_lake")
    parser.add_argument("--calls", type=int, default=10000)
    parser.add_argument("--floor-calls", type=int, default=4, help="calls of the small season whose localize is the floor")
    parser.add_argument("--file-s", type=float, default=600.0, help="length of each recording file, s")
    args = parser.parse_args()
    cfg = compose_cfg([f"+site={args.site}"])
    site = site_from_config(cfg.site)
    big, small = WORK / f"memory_{args.site}_{args.calls}", WORK / f"memory_{args.site}_floor_{args.floor_calls}"
    render(site, cfg, args.calls, args.file_s, big)
    render(site, cfg, args.floor_calls, args.file_s, small)
    out, floor_out = big / "season", small / "season"
    fit = measured(season_command(args.site, big, out, "protocol.stage=fit"))
    log.info("fitted in %.0f s", fit["wall_s"])
    localize = measured(season_command(args.site, big, out, "protocol.stage=localize"))
    baseline = measured(season_command(args.site, big, out, "protocol.stage=localize"))  # nothing left: imports + method
    floor_out.mkdir(parents=True)
    for name in (METHOD_FILE, DIGEST_FILE):  # the same fitted method, verified by its digest, as a shard gets it
        shutil.copy2(out / name, floor_out / name)
    measured(season_command(args.site, small, floor_out, "protocol.stage=fit"))
    floor = measured(season_command(args.site, small, floor_out, "protocol.stage=localize"))
    manifest = read_manifest(out)
    events = pd.read_parquet(out / EVENTS)
    floor_events = len(pd.read_parquet(floor_out / EVENTS))
    clip_samples = (events["end_s"] - events["start_s"]).max() * float(cfg.simulator.sample_rate_hz)
    chunk_audio_mib = manifest["chunk_events"] * site.n_mics * clip_samples * 4 / 2**20
    above_baseline = localize["peak_rss_mib"] - baseline["peak_rss_mib"]
    above_floor = localize["peak_rss_mib"] - floor["peak_rss_mib"]
    result = {"machine": machine(), "site": args.site, "calls": args.calls, "n_events": len(events), "floor_calls": args.floor_calls,
              "floor_events": floor_events, "chunk_events": manifest["chunk_events"], "batch_events": manifest["batch_events"],
              "chunk_audio_mib": chunk_audio_mib, "fit": fit, "localize": localize, "baseline": baseline, "floor": floor,
              "above_baseline_mib": above_baseline, "above_floor_mib": above_floor,
              "above_baseline_per_chunk_audio": above_baseline / chunk_audio_mib, "above_floor_per_chunk_audio": above_floor / chunk_audio_mib}
    lines = [f"# A season's peak memory above its floor ({args.site})", "",
             (f"`python benchmarks/bench_season_memory.py --site {args.site} --calls {args.calls} --floor-calls {args.floor_calls} "
             f"--file-s {args.file_s:g}` ({machine()['cpus']} CPUs; one run). `python -m acoustlab season` with its defaults (the lean "
             "feature set, the GCC's coarse search, the compiled solver), one localizing process each; peak RSS is the process' own "
             "VmHWM. Baseline: the same command once every chunk is done (interpreter, imports, the fitted method; no compiled "
             f"kernel is loaded). Floor: a season of {floor_events} events localized with the same fitted method in a fresh process "
             "(everything above plus the compiled kernels and one small batch)."), "",
             "| process | events | peak RSS (MiB) |", "|---|---|---|",
             f"| the season, localized | {len(events)} | {localize['peak_rss_mib']:.0f} |",
             f"| baseline (nothing left to do) | 0 | {baseline['peak_rss_mib']:.0f} |",
             f"| floor (a {floor_events}-event season) | {floor_events} | {floor['peak_rss_mib']:.0f} |", "",
             (f"One chunk ({manifest['chunk_events']} events; audio read in batches of {manifest['batch_events']}) holds "
             f"{chunk_audio_mib:.1f} MiB of clips. The season's peak is {above_baseline:.0f} MiB above the baseline "
             f"({above_baseline / chunk_audio_mib:.2f}× a chunk's audio) and {above_floor:.0f} MiB above the floor "
             f"({above_floor / chunk_audio_mib:.2f}×); the floor is {floor['peak_rss_mib'] - baseline['peak_rss_mib']:.0f} MiB above "
             "the baseline (the compiled kernels' runtime and one small batch).")]
    write_results(f"season_memory_{args.site}", result, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
