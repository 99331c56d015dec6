"""Behavioural checks over every YAML option of every plugin group (see acoustlab.run.plugin_checks).

Adding a YAML file to conf/simulator, features, solver, model, error_model, gate or conformal adds
its checks here without any other change.
"""

import pytest

from acoustlab.run.plugin_checks import CHECKS, CheckSkipped, plugin_checks
from acoustlab.run.registry import group_options

ALL = list(plugin_checks())


@pytest.mark.slow
@pytest.mark.parametrize("group,option,name,check", ALL, ids=[f"{g}={o}:{n}" for g, o, n, _ in ALL])
def test_plugin_behaves(group, option, name, check):
    try:
        check()
    except CheckSkipped as exc:
        pytest.skip(str(exc))


def test_every_option_of_every_checked_group_is_covered():
    covered = {(g, o) for g, o, _, _ in ALL}
    assert covered == {(g, o) for g in CHECKS for o in group_options(g)}


def test_a_broken_solver_fails_its_check(monkeypatch):
    """The solver check fails a solver that is not exact (the checks can fail)."""
    from acoustlab.run import plugin_checks as checks
    from plugins.solvers.hyperbolic import HyperbolicSolver

    original = HyperbolicSolver.solve

    def biased(self, inputs):
        result = original(self, inputs)
        result.position_m = result.position_m + 0.01
        return result

    monkeypatch.setattr(HyperbolicSolver, "solve", biased)
    with pytest.raises(AssertionError, match="noise-free"):
        checks.check_solver_exact("hyperbolic")


def test_a_gate_that_invents_positions_fails_its_check(monkeypatch):
    from acoustlab.core.contracts import GateDecision
    from acoustlab.run import plugin_checks as checks
    from plugins.gates.bounding_box import BoundingBoxGate

    def average(self, solver_position_m, model_position_m, features, site):
        return GateDecision((solver_position_m + model_position_m) / 2, solver_position_m[:, 0] > 0)

    monkeypatch.setattr(BoundingBoxGate, "decide", average)
    with pytest.raises(AssertionError, match="gate=bounding_box"):
        checks.check_gate("bounding_box")
