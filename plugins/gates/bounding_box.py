"""Bounding-box gate: keep the solver's estimate unless it falls outside the grown array box."""

from __future__ import annotations

import numpy as np
import pandas as pd

from acoustlab.core.contracts import GateDecision, StatelessGate
from acoustlab.core.types import Site
from acoustlab.toolkit.geometry import bounding_box


class BoundingBoxGate(StatelessGate):
    """Substitute the point model's estimate where the solver's is outside the box or not finite.

    Parameters
    ----------
    margin_fraction : float
        The mics' axis-aligned bounding box is grown on every side by this fraction of the largest
        mic-to-mic distance.
    """

    def __init__(self, margin_fraction: float = 0.25) -> None:
        self.margin_fraction = float(margin_fraction)

    def decide(self, solver_position_m: np.ndarray, model_position_m: np.ndarray, features: pd.DataFrame, site: Site) -> GateDecision:
        """See ``acoustlab.core.contracts.Gate``."""
        low, high = bounding_box(site.mic_positions_m, self.margin_fraction)
        finite = np.isfinite(solver_position_m).all(axis=1)
        inside = finite & (solver_position_m >= low).all(axis=1) & (solver_position_m <= high).all(axis=1)
        substituted = ~inside
        position = np.where(substituted[:, None], model_position_m, solver_position_m)
        return GateDecision(position_m=position, substituted=substituted)
