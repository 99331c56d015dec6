"""Positions as a map layer: a GeoPackage a GIS opens, in the CRS the mics were given in."""

import numpy as np
import pandas as pd
import pytest

from acoustlab.reporting.geo import write_geopackage

gpd = pytest.importorskip("geopandas")


def _positions(projected: bool) -> pd.DataFrame:
    table = pd.DataFrame(
        {
            "event_id": [0, 1, 2],
            "x_m": [10.0, 20.0, np.nan],
            "y_m": [5.0, 15.0, np.nan],
            "radius_gdop_scaled_0.8_m": [2.0, 4.0, np.nan],
            "radius_gdop_scaled_0.95_m": [3.0, 6.0, np.nan],
            "placed": [True, True, False],
            "radius_note": ["", "", ""],
        }
    )
    if projected:
        table.insert(3, "easting_m", table["x_m"] + 500000.0)
        table.insert(4, "northing_m", table["y_m"] + 4100000.0)
        table.insert(5, "crs", "EPSG:32633")
    return table


def test_a_geopackage_holds_every_column_in_the_mics_crs_and_the_radii_as_circles(tmp_path):
    table = _positions(projected=True)
    write_geopackage(table, tmp_path / "positions.gpkg")
    points = gpd.read_file(tmp_path / "positions.gpkg", layer="positions")
    assert points.crs.to_epsg() == 32633 and list(points.columns[:-1]) == list(table.columns)
    np.testing.assert_allclose(points.geometry.x[:2], [500010.0, 500020.0])
    assert points.geometry.iloc[2] is None or points.geometry.iloc[2].is_empty  # no position: no point
    radii = gpd.read_file(tmp_path / "positions.gpkg", layer="radii")
    assert len(radii) == 4 and set(radii["level"]) == {0.8, 0.95} and (radii["scorer"] == "gdop_scaled").all()
    np.testing.assert_allclose(radii.area, np.pi * radii["radius_m"] ** 2, rtol=0.01)
    centre = radii.geometry.centroid
    np.testing.assert_allclose(centre.x[radii["event_id"] == 1], 500020.0, atol=1e-6)


def test_positions_in_the_local_frame_have_no_crs_and_a_rewrite_replaces_the_file(tmp_path):
    path = tmp_path / "positions.gpkg"
    write_geopackage(_positions(projected=True), path)
    write_geopackage(_positions(projected=False), path)
    points = gpd.read_file(path, layer="positions")
    assert points.crs is None and len(points) == 3
    np.testing.assert_allclose(points.geometry.x[:2], [10.0, 20.0])
