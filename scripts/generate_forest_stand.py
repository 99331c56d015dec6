"""Generate the forest site's tree map (acoustlab/data/sites/forest_trees.csv).

The stand is GENERATED, not surveyed: a plausible old-growth mixed boreal stand for simulation.
Stem positions follow a Matérn cluster process thinned to a minimum spacing; species proportions
(Norway spruce, Scots pine, birch, aspen) and a reverse-J diameter distribution (truncated
exponential, 10–95 cm DBH) follow typical old-growth structure; ≈420 stems/ha with DBH ≥ 10 cm.

Run: python scripts/generate_forest_stand.py   (deterministic; seed below)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

SEED = 20261122
MICS_XY = np.array([[0.0, 0.0], [55.0, -5.0], [90.0, 25.0], [75.0, 70.0], [25.0, 75.0], [-10.0, 35.0]])
MARGIN_M = 40.0
STEMS_PER_HA = 420
MIN_SPACING_M = 1.2
SPECIES = {"picea_abies": 0.55, "pinus_sylvestris": 0.2, "betula_pendula": 0.15, "populus_tremula": 0.1}
MEAN_EXCESS_DBH_M = {"picea_abies": 0.16, "pinus_sylvestris": 0.22, "betula_pendula": 0.10, "populus_tremula": 0.18}


def main() -> None:
    rng = np.random.default_rng(SEED)
    low = MICS_XY.min(axis=0) - MARGIN_M
    high = MICS_XY.max(axis=0) + MARGIN_M
    area_ha = np.prod(high - low) / 1e4
    n_target = int(STEMS_PER_HA * area_ha)
    parents = rng.uniform(low, high, size=(n_target // 6, 2))
    stems: list[np.ndarray] = []
    while len(stems) < n_target:
        centre = parents[rng.integers(len(parents))] if rng.random() < 0.6 else rng.uniform(low, high)
        p = centre + rng.normal(0, 6.0, size=2) if rng.random() < 0.6 else rng.uniform(low, high)
        if not ((p >= low).all() and (p <= high).all()):
            continue
        if stems and np.min(np.linalg.norm(np.asarray(stems) - p, axis=1)) < MIN_SPACING_M:
            continue
        stems.append(p)
    xy = np.asarray(stems)
    species = rng.choice(list(SPECIES), size=len(xy), p=list(SPECIES.values()))
    dbh = np.array([0.10 + rng.exponential(MEAN_EXCESS_DBH_M[s]) for s in species])
    dbh = np.clip(dbh, 0.10, 0.95)
    # keep stems off the microphone poles
    keep = np.min(np.linalg.norm(xy[:, None] - MICS_XY[None], axis=2), axis=1) > 1.0
    table = pd.DataFrame(
        {"x_m": xy[keep, 0].round(2), "y_m": xy[keep, 1].round(2), "diameter_m": dbh[keep].round(3), "species": species[keep]}
    )
    out = Path(__file__).resolve().parent.parent / "acoustlab" / "data" / "sites" / "forest_trees.csv"
    out.parent.mkdir(parents=True, exist_ok=True)
    header = "# GENERATED stand (not surveyed): scripts/generate_forest_stand.py, seed %d\n" % SEED
    out.write_text(header + table.to_csv(index=False))
    print(f"{len(table)} trees over {area_ha:.2f} ha -> {out}")


if __name__ == "__main__":
    main()
