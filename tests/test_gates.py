"""Gates: τ* selection rule on a constructed case with a known answer, decisions, contracts."""

import numpy as np
import pandas as pd
import pytest

from acoustlab.core.types import NoiseRegime, Site
from plugins.gates.hybrid import HybridGate, select_tau
from plugins.gates.simple import ModelOnlyGate, SolverOnlyGate


def test_select_tau_known_answer():
    solver = np.concatenate([np.full(95, 1.0), np.full(5, 100.0)])  # p50 1, p99 100
    taus = np.array([1.0, 2.0, 3.0, 4.0])
    gated = np.stack([
        np.concatenate([np.full(95, 1.5), np.full(5, 5.0)]),   # τ=1: p99 ok but median +50 % → rejected
        np.concatenate([np.full(95, 1.1), np.full(5, 10.0)]),  # τ=2: ok (p99 ≤ 33, median +10 %)
        np.concatenate([np.full(95, 1.0), np.full(5, 30.0)]),  # τ=3: ok → the most permissive acceptable
        np.concatenate([np.full(95, 1.0), np.full(5, 60.0)]),  # τ=4: p99 too high → rejected
    ])
    tau, grid, met = select_tau(solver, gated, taus)
    assert met and tau == 3.0
    assert list(grid.columns) == ["tau_db", "p50_m", "p99_m"]
    tau, _, met = select_tau(solver, gated[[3]], taus[[3]])
    assert not met and tau == 4.0  # fallback: lowest p99 within the median tolerance


def site3():
    return Site("t", np.array([[0.0, 0, 1], [40, 0, 1], [20, 35, 1]]), np.zeros((0, 2)), np.zeros(0), (10, 10), (50, 50),
                "x", 100.0, "rigid", None, (NoiseRegime("white"),), (10, 10), ("synthetic",), (1.0, 1.0), 0.2)


def test_hybrid_gate_uses_box_then_energy():
    site = site3()
    truth = np.array([[20.0, 10.0], [10.0, 5.0], [25.0, 20.0]])
    d = np.sqrt(((np.column_stack([truth, np.ones(3)])[:, None] - site.mic_positions_m[None]) ** 2).sum(-1))
    levels = -20 * np.log10(d)
    solver = truth.copy()
    solver[1] = [500.0, 500.0]  # outside the box
    solver[2] = [2.0, 30.0]  # inside the box, but the levels say otherwise
    feats = pd.DataFrame({f"environment__level_{m}_db": levels[:, m] for m in range(3)})
    model = truth + 0.5
    decision = HybridGate(tau_db=1.0).decide(solver, model, feats, site)
    assert decision.substituted.tolist() == [False, True, True]
    np.testing.assert_allclose(decision.position_m[0], truth[0])


def test_simple_gates():
    s = np.array([[1.0, 1.0], [np.nan, np.nan]])
    m = np.array([[2.0, 2.0], [3.0, 3.0]])
    assert SolverOnlyGate().decide(s, m, pd.DataFrame(index=range(2)), site3()).substituted.tolist() == [False, True]
    assert ModelOnlyGate().decide(s, m, pd.DataFrame(index=range(2)), site3()).substituted.all()


def test_hybrid_gate_without_tau_or_levels_is_explained():
    from acoustlab.core.errors import DataError

    with pytest.raises(DataError, match="no τ"):
        HybridGate().decide(np.zeros((1, 2)), np.zeros((1, 2)), pd.DataFrame(index=[0]), site3())
    with pytest.raises(DataError, match="environment"):
        HybridGate(tau_db=3.0).decide(np.full((1, 2), 10.0), np.zeros((1, 2)), pd.DataFrame(index=[0]), site3())
