"""The season benchmark matches every localized event to the call it holds, also a call heard first by a nearby recorder."""

import sys
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parent.parent


def _bench_season():
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        import bench_season
    finally:
        sys.path.remove(str(REPO / "benchmarks"))
    return bench_season


def test_an_event_is_matched_to_its_own_call_even_when_its_source_is_next_to_a_recorder():
    bench = _bench_season()
    mics = np.array([[0.0, 0.0, 1.5], [60.0, 0.0, 1.5], [30.0, 50.0, 1.5]])
    c, margin = 330.0, 0.17
    # the second call is 1 m from recorder 0 (3 ms of travel, less than the selections' 0.02-s pad)
    truth = pd.DataFrame({"emission_s": [10.0, 12.3, 14.6], "x_m": [30.0, 1.0, 45.0], "y_m": [20.0, 0.0, 10.0], "z_m": [1.5, 1.5, 1.5]})
    travel = np.sqrt(((truth[["x_m", "y_m", "z_m"]].to_numpy()[:, None] - mics[None]) ** 2).sum(-1)).min(1) / c
    first_arrival = truth["emission_s"].to_numpy() + travel
    events = pd.DataFrame({"start_s": first_arrival - bench.RAVEN_PAD_S - margin})
    radii = {f"radius_gdop_scaled_{level}_m": 0.5 for level in ("0.5", "0.8", "0.95")}
    positions = pd.DataFrame({"x_m": truth["x_m"] + 0.1, "y_m": truth["y_m"], "solver_x_m": truth["x_m"], "solver_y_m": truth["y_m"],
                              "placed": True, **radii})

    out = bench.truth_errors(positions, events, truth, margin)

    assert out["n_matched_calls"] == 3
    assert out["method"]["share_over_5m"] == 0.0 and out["solver"]["share_over_5m"] == 0.0
    assert out["coverage_gdop_scaled_0.95"] == 1.0
