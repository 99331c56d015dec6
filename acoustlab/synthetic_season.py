"""``python -m acoustlab.synthetic_season --site forest --calls 200 --out DIR``: a synthetic season to try ``protocol=season`` on.

Writes one folder of long files per recorder (named by their start time), a Raven selection table
per recorder and ``truth.csv`` (``acoustlab.season.synthetic``).
"""

from __future__ import annotations

import logging
from pathlib import Path

from acoustlab.season.synthetic import SyntheticSeason, write_season

log = logging.getLogger("acoustlab.synthetic_season")


def main(argv: list[str] | None = None) -> int:
    """``python -m acoustlab.synthetic_season --site forest --calls 200 --out DIR``: write a synthetic season of a shipped site."""
    import argparse

    from acoustlab.run.plugin_checks import compose_config
    from acoustlab.stages.sites import site_from_config

    parser = argparse.ArgumentParser(
        prog="python -m acoustlab.synthetic_season",
        description="Write a synthetic season (long files per recorder, Raven tables, truth.csv) to try protocol=season.",
    )
    parser.add_argument("--site", default="forest", help="a site of conf/site (its mics, weather and source heights)")
    parser.add_argument("--calls", type=int, default=200, help="calls in the season")
    parser.add_argument("--file-s", type=float, default=600.0, help="length of each recording file, s")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True, help="folder to write audio/, raven/ and truth.csv into")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = compose_config([f"+site={args.site}"])
    site = site_from_config(cfg.site)
    settings = SyntheticSeason.for_site(
        site,
        duration_s=2.2 * args.calls + 5,
        file_s=args.file_s,
        n_calls=args.calls,
        min_spacing_s=2.0,
        sample_rate_hz=float(cfg.simulator.sample_rate_hz),
        seed=args.seed,
    )
    out = Path(args.out)
    truth = write_season(settings, out)
    truth.to_csv(out / "truth.csv", index=False)
    log.info(
        "wrote %d calls over %.1f h for %d recorders to %s (audio/, raven/, truth.csv)",
        len(truth),
        settings.duration_s / 3600,
        len(site.mic_positions_m),
        out,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
