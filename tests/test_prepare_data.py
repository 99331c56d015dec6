"""One entry point prepares a run's data: the app and the benchmarks get the same tables, bound included."""

import numpy as np
import pytest

from acoustlab.core import columns as col
from acoustlab.run.app import build_run, prepare_data, solver_features
from acoustlab.stages.solver_columns import add_solver_columns


@pytest.mark.slow
def test_prepare_data_applies_the_plausible_bound_a_run_applies(compose_cfg, tmp_path):
    cfg = compose_cfg(
        [
            "+site=frozen_lake",
            "+experiment=smoke",
            f"paths.outputs_dir={tmp_path}",
            "tracking=none",
            "pipeline.plausible_margin_fraction=0.0",
        ]
    )  # a tight region: some fixes fall outside it
    built = build_run(cfg)
    data = prepare_data(cfg, built)
    assert data is not None and data.field_data is None
    table = data.dataset.features
    outside = table[col.SOLVER_FAILURE].to_numpy() == 2
    assert outside.any(), "a zero margin must put some fixes outside the plausible region"
    assert np.isnan(table.loc[outside, list(col.SOLVER_ESTIMATE_COLUMNS)].to_numpy()).all()  # never emitted as a number
    unbounded = add_solver_columns(
        table.drop(columns=[c for c in table if c.startswith("solver__")]), data.dataset.events, built.site, built.components.solver
    )
    assert np.isfinite(unbounded.loc[outside, list(col.SOLVER_ESTIMATE_COLUMNS)].to_numpy()).all()  # the bound did it
    again = solver_features(
        cfg,
        unbounded.drop(columns=[c for c in unbounded if c.startswith("solver__")]),
        data.dataset.events,
        built.site,
        built.components.solver,
    )
    assert again.equals(table)  # the helper benchmarks use to compare solvers gives the run's table
