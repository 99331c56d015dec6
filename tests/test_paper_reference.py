"""The paper's published figures beside a run's: the experiments carry them and the table reads metrics.json paths."""

import numpy as np
import pytest
from omegaconf import OmegaConf

from acoustlab.reporting.paper import paper_comparison


@pytest.mark.parametrize("experiment,site", [("paper_forest", "forest"), ("paper_frozen_lake", "frozen_lake")])
def test_paper_experiments_carry_the_published_figures(compose_cfg, experiment, site):
    cfg = compose_cfg([f"+site={site}", f"+experiment={experiment}"])
    reference = OmegaConf.to_container(cfg.paper_reference, resolve=True)
    assert reference["source"] and reference["note"] and reference["figures"]["errors.solver.p50"] > 0
    assert "learned" in cfg.pipeline.extra_gates  # the best measured gate beside the paper's


def test_paper_comparison_reads_dotted_paths_including_level_keys():
    metrics = {"errors": {"solver": {"p50": 0.07, "p99": float("inf")}}, "coverage": {"gdop_scaled": {"0.8": 0.79}},
               "spearman_rho": {"gdop": None}}
    rows, lines = paper_comparison({"source": "s", "note": "n", "figures": {"errors.solver.p50": 0.14, "errors.solver.p99": 71.4,
                                                                             "coverage.gdop_scaled.0.8": 0.78, "spearman_rho.gdop": 0.22}}, metrics)
    by = {r["quantity"]: r for r in rows}
    assert by["errors.solver.p50"]["ours"] == 0.07 and by["errors.solver.p50"]["ratio"] == pytest.approx(0.5)
    assert by["coverage.gdop_scaled.0.8"]["ours"] == 0.79
    assert np.isnan(by["spearman_rho.gdop"]["ours"]) and by["errors.solver.p99"]["ours"] == np.inf
    assert any("| `coverage.gdop_scaled.0.8` | 0.78 | 0.79 |" in line for line in lines)
