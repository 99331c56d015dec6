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
    metrics = {
        "errors": {"solver": {"p50": 0.07, "p99": float("inf")}},
        "coverage": {"gdop_scaled": {"0.8": 0.79}},
        "spearman_rho": {"gdop": None},
    }
    rows, lines = paper_comparison(
        {
            "source": "s",
            "note": "n",
            "figures": {"errors.solver.p50": 0.14, "errors.solver.p99": 71.4, "coverage.gdop_scaled.0.8": 0.78, "spearman_rho.gdop": 0.22},
        },
        metrics,
    )
    by = {r["quantity"]: r for r in rows}
    assert by["errors.solver.p50"]["ours"] == 0.07 and by["errors.solver.p50"]["ratio"] == pytest.approx(0.5)
    assert by["coverage.gdop_scaled.0.8"]["ours"] == 0.79
    assert np.isnan(by["spearman_rho.gdop"]["ours"]) and by["errors.solver.p99"]["ours"] == np.inf
    assert any("| `coverage.gdop_scaled.0.8` | 0.78 | 0.79 |" in line for line in lines)


def test_forest_is_compared_with_the_papers_simulation_figures_only(compose_cfg):
    """Like with like: the paper's coverage and Spearman figures are from its frozen-lake field study."""
    forest = compose_cfg(["+site=forest", "+experiment=paper_forest"]).paper_reference.figures
    lake = compose_cfg(["+site=frozen_lake", "+experiment=paper_frozen_lake"]).paper_reference.figures
    assert all(k.startswith("errors.") for k in forest)
    assert {"coverage.gdop_scaled.0.95", "spearman_rho.error_model", "spearman_rho.gdop"} <= set(lake)


@pytest.mark.parametrize("experiment,site", [("paper_forest", "forest"), ("paper_frozen_lake", "frozen_lake")])
def test_the_papers_method_as_written_leaves_only_what_cannot_be_matched(compose_cfg, experiment, site):
    from acoustlab.reporting.paper import deviations

    ours = deviations(OmegaConf.to_container(compose_cfg([f"+site={site}", f"+experiment={experiment}"]), resolve=True))
    as_written = deviations(OmegaConf.to_container(compose_cfg([f"+site={site}", f"+experiment={experiment}_as_written"]), resolve=True))
    for topic in (
        "first stage",
        "GCC weighting",
        "gate's context",
        "leave one position out",
        "τ* rule",
        "trust check",
        "GDOP clipped",
        "allowance",
    ):
        assert any(topic in d for d in ours), topic  # every deviation of our defaults is named …
        assert not any(topic in d for d in as_written), topic  # … and the as-written experiment removes it
    assert any("point model" in d for d in as_written) and any("simulator" in d for d in as_written)  # what remains is said


def test_the_tau_rule_can_compare_with_the_bare_solver():
    from acoustlab.core.errors import ConfigError
    from plugins.gates.hybrid import HybridGate

    with pytest.raises(ConfigError, match="tau_reference must be 'box'.*or 'solver'"):
        HybridGate(tau_reference="bare")
    assert HybridGate(tau_reference="solver").tau_reference == "solver"
