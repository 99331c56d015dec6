"""Positions as a map layer: ``positions.gpkg``, readable by QGIS, R's ``sf::st_read`` and ``geopandas.read_file``.

Two layers: ``positions``, one point per detection with every column of ``positions.csv`` (an
empty geometry where it has no position, every scorer's radii as attributes), and ``radii``, one
circle per placed detection and level of the map's scorer (GDOP-scaled where the run has it, as
the site map; ``radius_<scorer>_<level>_m``). Where the mics table gave projected coordinates
(``easting_m, northing_m`` and a ``crs``), the points and circles are in that CRS (the map from
the local frame is rigid, so a radius is a circle there too); otherwise they are in the site's
local frame, in metres, with no CRS. Written with geopandas (the ``gis`` extra:
``pip install -e ".[gis]"``); without it, the run says in one line that it wrote none.
"""

from __future__ import annotations

import logging
import re
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from acoustlab.core import columns as col

log = logging.getLogger(__name__)

#: The GeoPackage beside positions.csv.
GEOPACKAGE = "positions.gpkg"
#: ``radius_<scorer>_<level>_m``, the positions table's radius columns.
RADIUS_COLUMN = re.compile(r"^radius_(?P<scorer>.+)_(?P<level>[0-9.]+)_m$")
#: Vertices per quarter circle of a radius polygon.
QUARTER_SEGMENTS = 8


def write_geopackage(positions: pd.DataFrame, path: Path) -> Path | None:
    """Write ``positions`` (a positions table) as ``path`` (layers ``positions`` and ``radii``); None without geopandas.

    Raises
    ------
    ValueError
        Where the table holds more than one CRS.
    """
    try:
        import geopandas as gpd
    except ImportError:
        log.info('%s not written: the map layer needs geopandas (pip install -e ".[gis]")', path.name)
        return None
    xy_columns = ["easting_m", "northing_m"] if {"easting_m", "northing_m"} <= set(positions.columns) else [col.TRUE_X, col.TRUE_Y]
    crs = None
    if "crs" in positions and positions["crs"].notna().any():
        named = positions["crs"].dropna().astype(str).unique()
        if len(named) > 1:
            raise ValueError(f"the positions name {len(named)} CRS ({', '.join(named)}); a layer has one")
        crs = named[0]
    xy = positions[xy_columns].to_numpy(float)
    points = gpd.points_from_xy(xy[:, 0], xy[:, 1])
    placed = np.isfinite(xy).all(axis=1)
    points = np.where(placed, points, None)
    layer = gpd.GeoDataFrame(positions.reset_index(drop=True), geometry=list(points), crs=crs)
    path.unlink(missing_ok=True)  # a GeoPackage is appended to by layer: start from nothing
    circles = _radius_circles(positions, xy, placed)
    with warnings.catch_warnings():  # the local frame has no CRS by design; the log line below says which frame it is
        warnings.filterwarnings("ignore", message="'crs' was not provided")
        layer.to_file(path, layer="positions", driver="GPKG")
        if len(circles):
            gpd.GeoDataFrame(
                circles.drop(columns=["x", "y"]),
                geometry=gpd.points_from_xy(circles["x"], circles["y"]).buffer(circles["radius_m"].to_numpy(float), QUARTER_SEGMENTS),
                crs=crs,
            ).to_file(path, layer="radii", driver="GPKG")
    log.info(
        "map layer: %s (%d positions, %d radius circles%s)", path, int(placed.sum()), len(circles), f", {crs}" if crs else ", local frame"
    )
    return path


def _radius_circles(positions: pd.DataFrame, xy: np.ndarray, placed: np.ndarray) -> pd.DataFrame:
    """One row per placed detection, scorer and level with a finite radius: ``event_id, scorer, level, radius_m, x, y``."""
    matches = [m for m in map(RADIUS_COLUMN.match, positions.columns) if m is not None]
    if not matches:
        return pd.DataFrame()
    shown = min({m["scorer"] for m in matches}, key=lambda s: (s != "gdop_scaled", s))  # the map's scorer: one circle per level
    rows = []
    for match in matches:
        if match["scorer"] != shown:
            continue
        name = match.string
        radius = positions[name].to_numpy(float)
        keep = placed & np.isfinite(radius) & (radius > 0)
        rows.append(
            pd.DataFrame(
                {
                    col.EVENT_ID: positions[col.EVENT_ID].to_numpy()[keep],
                    "scorer": match["scorer"],
                    "level": float(match["level"]),
                    "radius_m": radius[keep],
                    "x": xy[keep, 0],
                    "y": xy[keep, 1],
                }
            )
        )
    return pd.concat(rows, ignore_index=True) if rows else pd.DataFrame()
