"""A mics table's place on the map: latitude/longitude in, a local metric frame inside, map coordinates out.

acoustlab computes in a local frame in metres (``x_m, y_m``). A mics table may also say where the
mics are on the map, one of two ways:

* ``latitude, longitude`` (WGS 84 degrees, as a GPS shows them): projected with pyproj to the UTM
  zone of the array's centre (``easting_m, northing_m`` and that zone's ``crs``, e.g.
  ``EPSG:32617``); where the table has no ``x_m, y_m`` they are the UTM coordinates less the
  array's centre rounded to whole metres (so the local frame is exact and easy to read);
* ``easting_m, northing_m`` and a ``crs`` (any projected CRS in metres, as a GIS exports them).

``map_projection`` fits the rigid map (rotation and shift, no scale) from the local frame to those
map coordinates, checked to agree within 0.5 m; positions are then written in map coordinates too,
and in latitude/longitude where the mics were given so. A UTM zone's scale error over an array a
few hundred metres across is below 1 mm per 100 m (the zone's scale factor is 0.9996 at its
centre): the local frame and the map agree to well within that tolerance.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from acoustlab.core import columns as col
from acoustlab.core.errors import DataError, show

LATITUDE, LONGITUDE = "latitude", "longitude"
EASTING, NORTHING, CRS = "easting_m", "northing_m", "crs"
#: How far the local and the map coordinates of one mic may disagree after the best rigid fit, m.
AGREEMENT_M = 0.5


def _pyproj(where: str) -> Any:
    """pyproj, imported only where a table needs it (the ``gis`` extra)."""
    try:
        import pyproj
    except ImportError:
        raise DataError(f'{where}: latitude/longitude need pyproj (pip install -e ".[gis]")') from None
    return pyproj


def utm_crs(latitude_deg: float, longitude_deg: float) -> str:
    """The WGS 84 UTM zone holding a point, as ``EPSG:326NN`` (north) or ``EPSG:327NN`` (south).

    The plain 6° zones: Norway's and Svalbard's wider zones are a map convention, and the zone beside
    them is as metric over an array (scale within 0.1 %)."""
    zone = int(np.floor((longitude_deg + 180.0) / 6.0)) % 60 + 1
    return f"EPSG:{(32600 if latitude_deg >= 0 else 32700) + zone}"


def _degrees(table: pd.DataFrame, where: str, every_row: bool) -> tuple[np.ndarray, np.ndarray]:
    """(latitude, longitude) of ``table``, degrees; with ``every_row`` false an empty cell is NaN (a row without a spot).

    Raises
    ------
    DataError
        Naming ``where``, the line and the column of the first value that is not a latitude in
        [−90, 90] or a longitude in [−180, 180] (an empty cell too, with ``every_row``).
    """
    values = []
    for name, limit in ((LATITUDE, 90.0), (LONGITUDE, 180.0)):
        raw = table[name]
        v = pd.to_numeric(raw, errors="coerce").to_numpy(float)
        given = np.ones(len(raw), bool) if every_row else raw.notna().to_numpy() & (raw.astype(str).str.strip() != "").to_numpy()
        bad = given & (~np.isfinite(v) | (np.abs(v) > limit))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise DataError(
                f"{where}, line {i + 2}, column '{name}': {show(raw.iloc[i])} is not a number in [-{limit:g}, {limit:g}] degrees"
            )
        values.append(np.where(given, v, np.nan))
    return values[0], values[1]


def with_map_coordinates(mics: pd.DataFrame, where: str) -> pd.DataFrame:
    """``mics`` with ``easting_m, northing_m, crs`` from its ``latitude, longitude`` (and ``x_m, y_m`` where it has none).

    A table without latitude/longitude is returned as it is.

    Raises
    ------
    DataError
        Naming ``where`` (the file), the line and column of a value that is not a latitude in [−90, 90]
        or a longitude in [−180, 180], or a table giving both latitude/longitude and easting/northing.
    """
    if not {LATITUDE, LONGITUDE} & set(mics.columns):
        return mics
    if not {LATITUDE, LONGITUDE} <= set(mics.columns):
        raise DataError(f"{where}: give both '{LATITUDE}' and '{LONGITUDE}' (WGS 84 degrees), or neither")
    if {EASTING, NORTHING} & set(mics.columns):
        raise DataError(f"{where}: give the mics on the map once: latitude/longitude or easting_m/northing_m with a crs, not both")
    lat, lon = _degrees(mics, where, every_row=True)
    crs = utm_crs(float(np.mean(lat)), float(np.mean(lon)))
    transformer = _pyproj(where).Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    easting, northing = transformer.transform(lon, lat)
    out = mics.copy()
    out[EASTING], out[NORTHING], out[CRS] = np.asarray(easting, float), np.asarray(northing, float), crs
    if not {col.MIC_X, col.MIC_Y} & set(mics.columns):
        centre = np.round([np.mean(out[EASTING]), np.mean(out[NORTHING])])
        out[col.MIC_X], out[col.MIC_Y] = out[EASTING] - centre[0], out[NORTHING] - centre[1]
    return out


def map_projection(mics: pd.DataFrame, where: str) -> tuple[np.ndarray, np.ndarray, str, bool] | None:
    """The rigid map from the mics' local frame to their map coordinates, or None where the table gives none.

    Returns
    -------
    (rotation, translation, crs, geographic) or None
        ``map = local @ rotation.T + translation`` (2×2, 2 values, m), the CRS text ('' where none is
        named), and whether the mics were given in latitude/longitude (positions are then too).

    Raises
    ------
    DataError
        Where the two sets of coordinates of a mic disagree by more than ``AGREEMENT_M`` after the best fit.
    """
    if not {EASTING, NORTHING} <= set(mics.columns):
        return None
    local = mics[[col.MIC_X, col.MIC_Y]].to_numpy(float)
    projected = mics[[EASTING, NORTHING]].apply(pd.to_numeric, errors="coerce").to_numpy(float)
    if not np.isfinite(projected).all():
        i, j = np.argwhere(~np.isfinite(projected))[0]
        raise DataError(f"{where}, line {i + 2}, column '{(EASTING, NORTHING)[j]}': not a finite number (m)")
    lc, pc = local.mean(axis=0), projected.mean(axis=0)
    u, _, vt = np.linalg.svd((projected - pc).T @ (local - lc))
    rotation = u @ np.diag([1.0, np.sign(np.linalg.det(u @ vt))]) @ vt  # Kabsch, a proper rotation
    translation = pc - lc @ rotation.T
    residual = np.linalg.norm(local @ rotation.T + translation - projected, axis=1)
    if residual.max() > AGREEMENT_M:
        worst = int(residual.argmax())
        raise DataError(
            f"{where}, line {worst + 2}: x_m, y_m and easting_m, northing_m disagree by {residual[worst]:.2f} m after the best "
            "rotation and shift; both must describe the same mic positions in metres"
        )
    crs = str(mics[CRS].dropna().iloc[0]) if CRS in mics and mics[CRS].notna().any() else ""
    return rotation, translation, crs, LATITUDE in mics.columns


def geographic_of(easting_m: np.ndarray, northing_m: np.ndarray, crs: str) -> tuple[np.ndarray, np.ndarray]:
    """(latitude, longitude) in WGS 84 degrees of map coordinates in ``crs`` (NaN stays NaN)."""
    transformer = _pyproj(f"crs {crs}").Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    lon, lat = transformer.transform(np.asarray(easting_m, float), np.asarray(northing_m, float))
    return np.asarray(lat, float), np.asarray(lon, float)


def spots_in_local_frame(events: pd.DataFrame, mics: pd.DataFrame, where: str) -> pd.DataFrame:
    """``events`` with the local ``x_m, y_m`` of spots given by ``latitude, longitude`` (as it is without them).

    A row without a latitude/longitude (a detection of unknown position) gets none. The spots go
    through the mics' own map (``map_projection``), so a spot and a mic surveyed at one point agree.

    Raises
    ------
    DataError
        Naming ``where``: spots in latitude/longitude beside ``x_m, y_m``, or where the mics are not
        given on the map; or the line and column of a value out of range.
    """
    if not {LATITUDE, LONGITUDE} & set(events.columns):
        return events
    if not {LATITUDE, LONGITUDE} <= set(events.columns):
        raise DataError(f"{where}: give both '{LATITUDE}' and '{LONGITUDE}' (WGS 84 degrees) of the spots, or neither")
    if {col.TRUE_X, col.TRUE_Y} & set(events.columns):
        raise DataError(f"{where}: give the spots once: latitude/longitude or x_m/y_m, not both")
    projection = map_projection(mics, where)
    if projection is None or not projection[2]:
        raise DataError(
            f"{where}: spots in latitude/longitude need the mics on the map (latitude/longitude, or easting_m/northing_m and a crs)"
        )
    rotation, translation, crs, _ = projection
    latitude, longitude = _degrees(events, where, every_row=False)
    transformer = _pyproj(where).Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    easting, northing = transformer.transform(longitude, latitude)
    local = (np.c_[easting, northing] - translation) @ rotation  # the inverse of map = local @ rotation.T + translation
    out = events.copy()
    out[col.TRUE_X], out[col.TRUE_Y] = local[:, 0], local[:, 1]
    return out
