"""Trivial gates for comparison: always the solver, or always the point model."""

from __future__ import annotations

import numpy as np
import pandas as pd

from acoustlab.core.contracts import GateDecision, StatelessGate
from acoustlab.core.types import Site


class SolverOnlyGate(StatelessGate):
    """Keep the solver's estimate everywhere (the model's only where the solver gave none)."""

    def decide(self, solver_position_m: np.ndarray, model_position_m: np.ndarray, features: pd.DataFrame, site: Site) -> GateDecision:
        """See ``acoustlab.core.contracts.Gate``."""
        missing = ~np.isfinite(solver_position_m).all(axis=1)
        return GateDecision(np.where(missing[:, None], model_position_m, solver_position_m), missing)


class ModelOnlyGate(StatelessGate):
    """Take the point model's estimate everywhere."""

    def decide(self, solver_position_m: np.ndarray, model_position_m: np.ndarray, features: pd.DataFrame, site: Site) -> GateDecision:
        """See ``acoustlab.core.contracts.Gate``."""
        return GateDecision(np.asarray(model_position_m, dtype=float).copy(), np.ones(len(model_position_m), dtype=bool))
