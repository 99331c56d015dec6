"""What a run knows, before anything is fitted, about placing field detections: the solver stage's rules and the map.

Part of ``acoustlab.method.pipeline.Components`` (``placement``); used by ``acoustlab.method.localizer``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.stages.field_calibration import FieldCalibration
from acoustlab.toolkit.map_frame import CRS, EASTING, LATITUDE, LONGITUDE, NORTHING, geographic_of


@dataclass(frozen=True)
class MapProjection:
    """The rigid map from the site's local frame to a mics table's projected coordinates (``field.mics_csv`` with
    ``easting_m, northing_m``): ``projected = local @ rotation.T + translation``, both in m."""

    rotation: np.ndarray
    translation: np.ndarray
    crs: str
    #: the mics were given in latitude/longitude: positions are written so too
    geographic: bool = False

    def add_columns(self, table: pd.DataFrame) -> pd.DataFrame:
        """``table`` with ``easting_m, northing_m, crs`` (and ``latitude, longitude`` where the mics were given so) right after
        its ``y_m`` (NaN where ``x_m, y_m`` are)."""
        projected = table[[col.TRUE_X, col.TRUE_Y]].to_numpy(float) @ self.rotation.T + self.translation
        at = table.columns.get_loc(col.TRUE_Y) + 1
        table.insert(at, EASTING, projected[:, 0])
        table.insert(at + 1, NORTHING, projected[:, 1])
        table.insert(at + 2, CRS, self.crs)
        if self.geographic:
            latitude, longitude = geographic_of(projected[:, 0], projected[:, 1], self.crs)
            table.insert(at + 3, LATITUDE, latitude)
            table.insert(at + 4, LONGITUDE, longitude)
        return table


@dataclass(frozen=True)
class PlacementRules:
    """How a run solves field detections and reports them, known before anything is fitted (``Components.placement``).

    Attributes
    ----------
    plausible_margin_fraction : float or None
        ``pipeline.plausible_margin_fraction``: fixes beyond the array grown by this fraction of its extent are failures.
    calibration : FieldCalibration, optional
        ``calibration=PATH``: its thermometer offset and clocks are applied before the solver (the site is already its array).
    min_gcc_peak : float, optional
        ``features.gcc.min_peak``: a recorder without a GCC peak that high with another is left out of the solve.
    min_gcc_peak_relative : float, optional
        ``features.gcc.min_peak_relative``: the same, with the height a share of the event's strongest pair peak.
    projection : MapProjection, optional
        Positions are also written in the mics table's projected coordinates.
    """

    plausible_margin_fraction: float | None = None
    calibration: FieldCalibration | None = None
    min_gcc_peak: float | None = None
    min_gcc_peak_relative: float | None = None
    projection: MapProjection | None = None
