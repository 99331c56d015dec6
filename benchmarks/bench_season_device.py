"""A season localized end to end with the GCC on a GPU against the CPU path: one run, one machine.

Usage (on a machine with a CUDA GPU, torch and XGBoost)::

    python benchmarks/bench_season_device.py [--site forest] [--calls 1000] [--device cuda]

Renders one synthetic season with ``bench_season.py``'s settings (calls rendered into long noise
files per recorder, Raven tables per recorder), then for each feature configuration,
``features=physics_lean`` on the CPU and the same with ``+features.gcc.device=cuda``: fits the
method once (``protocol.stage=fit``: simulation, features and models), localizes every detection in
one process (``protocol.stage=localize``), runs the same command again with nothing left to do
(the baseline: imports and loading the method), merges, and scores the positions against the
rendered calls with ``bench_season.truth_errors``. Detections per second are given in wall time
(what a user waits; the GPU's work is not CPU time) and in CPU time of the process, both above the
baseline. Writes benchmarks/results/season_device.{json,md}.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time
from pathlib import Path

import pandas as pd
from bench_season import WORK, measured, season_command, truth_errors
from common import compose_cfg, machine, write_results

from acoustlab.season.protocol import SeasonLocalize
from acoustlab.season.stream import EVENTS
from acoustlab.season.synthetic import SyntheticSeason, write_season
from acoustlab.stages.sites import site_from_config

log = logging.getLogger("bench_season_device")


def run_config(site_name: str, folder: Path, name: str, overrides: list[str], truth: pd.DataFrame, margin_s: float) -> dict:
    """Fit, localize, baseline and merge one configuration; its timings and accuracy."""
    out = folder / f"season_{name}"
    command = lambda *extra: season_command(site_name, folder, out, *overrides, *extra)  # noqa: E731
    fit = measured(command("protocol.stage=fit"))
    localize = measured(command("protocol.stage=localize"))
    baseline = measured(command("protocol.stage=localize"))  # every chunk done: imports and the method only
    measured(command("protocol.stage=merge"))
    positions = pd.read_parquet(Path(f"{out}_run") / "positions.parquet")
    events = pd.read_parquet(out / EVENTS)
    n = len(events)
    row = {"overrides": overrides, "n_events": n, "fit": fit, "localize": localize, "baseline": baseline,
           "detections_per_s_wall": n / max(localize["wall_s"] - baseline["wall_s"], 1e-9),
           "detections_per_s_cpu": n / max(localize["cpu_s"] - baseline["cpu_s"], 1e-9),
           "accuracy": truth_errors(positions, events, truth, margin_s)}
    log.info("%s: %.1f detections/s wall, %.1f CPU; fit %.0f s", name, row["detections_per_s_wall"], row["detections_per_s_cpu"], fit["wall_s"])
    return row


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--site", default="forest")
    parser.add_argument("--calls", type=int, default=1000)
    parser.add_argument("--file-s", type=float, default=600.0)
    parser.add_argument("--device", default="cuda")
    opts = parser.parse_args()
    cfg = compose_cfg([f"+site={opts.site}"])
    site = site_from_config(cfg.site)
    settings = SyntheticSeason.for_site(site, duration_s=2.2 * opts.calls + 5, file_s=opts.file_s, n_calls=opts.calls, min_spacing_s=2.0,
                                        sample_rate_hz=float(cfg.simulator.sample_rate_hz), seed=opts.calls)
    folder = WORK / f"device_{opts.site}_{opts.calls}"
    if folder.exists():
        shutil.rmtree(folder)
    start = time.perf_counter()
    truth = write_season(settings, folder)
    render_s = time.perf_counter() - start
    margin_s = SeasonLocalize({}, {"format": "raven"}, {}).margin_s(site)
    configs = {"cpu": ["features=physics_lean"], opts.device: ["features=physics_lean", f"+features.gcc.device={opts.device}"]}
    rows = {name: run_config(opts.site, folder, name, overrides, truth, margin_s) for name, overrides in configs.items()}
    gpu = "none"
    if opts.device.startswith("cuda"):
        import torch

        gpu = torch.cuda.get_device_name(torch.device(opts.device))
    lines = ["# A season end to end with the GCC on a GPU against the CPU (one run, one machine)", "",
             f"`python benchmarks/bench_season_device.py --site {opts.site} --calls {opts.calls} --device {opts.device}`: a synthetic "
             f"{opts.site} season of {opts.calls} calls ({settings.duration_s / 3600:.2f} h, rendered in {render_s:.0f} s), "
             f"`python -m acoustlab season` with `features=physics_lean`, one localizing process; GPU: {gpu}; "
             f"{machine()['cpus']} CPU cores. Rates are above the baseline (the same command with every chunk done).", "",
             "| GCC on | detections | detections/s (wall) | detections/s (CPU) | fit (wall, s) | method > 5 m | solver > 5 m | GDOP-scaled 0.95 radii cover |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        acc = r["accuracy"]
        lines.append(f"| {name} | {r['n_events']} | {r['detections_per_s_wall']:.1f} | {r['detections_per_s_cpu']:.1f} | "
                     f"{r['fit']['wall_s']:.0f} | {100 * acc['method']['share_over_5m']:.1f} % | {100 * acc['solver']['share_over_5m']:.1f} % | "
                     f"{100 * acc['coverage_gdop_scaled_0.95']:.1f} % |")
    cpu, dev = rows["cpu"], rows[opts.device]
    lines += ["", f"Wall-time rate {dev['detections_per_s_wall'] / cpu['detections_per_s_wall']:.2f}× the CPU path's."]
    write_results("season_device", {"machine": machine(), "site": opts.site, "calls": opts.calls, "device": opts.device, "gpu": gpu,
                                    "render_s": render_s, "configs": rows}, lines)
    log.info("\n".join(lines))


if __name__ == "__main__":
    main()
