"""Mics on the map: latitude/longitude in, a local metric frame inside, map coordinates and latitude/longitude out."""

import numpy as np
import pandas as pd
import pytest

from acoustlab.core.errors import DataError
from acoustlab.method.placement_rules import MapProjection
from acoustlab.toolkit.map_frame import map_projection, utm_crs, with_map_coordinates

pyproj = pytest.importorskip("pyproj")

#: Four recorders around a marsh in Ohio (UTM 17 N), about 40 m apart, as a GPS shows them.
LAT_LON = [(41.30000, -81.60000), (41.30000, -81.59952), (41.30036, -81.59952), (41.30036, -81.60000)]


def gps_table(**extra):
    lat, lon = np.array(LAT_LON).T
    return pd.DataFrame({"mic_id": list("ABCD"), "latitude": lat, "longitude": lon, "z_m": 1.5, **extra})


def test_mics_in_latitude_longitude_get_a_local_frame_whose_distances_are_the_ground_s():
    mics = with_map_coordinates(gps_table(), "mics.csv")
    assert (mics["crs"] == "EPSG:32617").all()
    geod = pyproj.Geod(ellps="WGS84")
    lat, lon = np.array(LAT_LON).T
    for i in range(4):
        for j in range(i + 1, 4):
            ground = geod.inv(lon[i], lat[i], lon[j], lat[j])[2]
            local = np.hypot(*(mics.loc[i, ["x_m", "y_m"]].to_numpy(float) - mics.loc[j, ["x_m", "y_m"]].to_numpy(float)))
            assert abs(local - ground) < 1e-3 * ground  # UTM's scale error: 0.9996–1.001 within a zone
    np.testing.assert_allclose(mics[["x_m", "y_m"]].mean(), 0.0, atol=1.0)  # the centre, rounded to whole metres
    rotation, translation, crs, geographic = map_projection(mics, "mics.csv")
    np.testing.assert_allclose(rotation, np.eye(2), atol=1e-12)
    assert translation == pytest.approx(np.round(translation)) and crs == "EPSG:32617" and geographic
    # and back: a position at a mic's local coordinates is that mic's latitude and longitude
    table = mics[["x_m", "y_m"]].copy()
    back = MapProjection(rotation, translation, crs, geographic).add_columns(table)
    np.testing.assert_allclose(back[["latitude", "longitude"]], LAT_LON, atol=1e-9)
    assert list(back.columns) == ["x_m", "y_m", "easting_m", "northing_m", "crs", "latitude", "longitude"]


def test_local_coordinates_given_beside_latitude_longitude_are_checked_against_them():
    local = with_map_coordinates(gps_table(), "mics.csv")[["x_m", "y_m"]]
    rotated = local.to_numpy() @ np.array([[0.0, -1.0], [1.0, 0.0]]).T + [100.0, -7.0]  # the user's own frame
    mics = with_map_coordinates(gps_table(x_m=rotated[:, 0], y_m=rotated[:, 1]), "mics.csv")
    np.testing.assert_allclose(mics[["x_m", "y_m"]], rotated)  # the user's frame is kept
    assert map_projection(mics, "mics.csv")[0] @ [1.0, 0.0] == pytest.approx([0.0, -1.0], abs=1e-6)
    off = gps_table(x_m=rotated[:, 0], y_m=rotated[:, 1] + [0.0, 0.0, 0.0, 2.0])
    with pytest.raises(DataError, match=r"mics.csv, line 5: x_m, y_m and easting_m, northing_m disagree by"):
        map_projection(with_map_coordinates(off, "mics.csv"), "mics.csv")


@pytest.mark.parametrize(
    ("table", "message"),
    [
        (
            gps_table().assign(latitude=[41.3, 91.0, 41.3, 41.3]),
            r"mics.csv, line 3, column 'latitude': 91.0 is not a number in \[-90, 90\]",
        ),
        (gps_table().assign(longitude=["-81.6", "x", "-81.6", "-81.6"]), r"line 3, column 'longitude': 'x' is not a number"),
        (gps_table().drop(columns="longitude"), "give both 'latitude' and 'longitude'"),
        (gps_table(easting_m=0.0, northing_m=0.0), "latitude/longitude or easting_m/northing_m with a crs, not both"),
    ],
)
def test_a_bad_latitude_or_longitude_is_named_in_one_line(table, message):
    with pytest.raises(DataError, match=message):
        with_map_coordinates(table, "mics.csv")


def test_the_utm_zone_is_the_one_holding_the_array():
    assert [utm_crs(41.3, -81.6), utm_crs(-33.9, 151.2), utm_crs(52.0, 5.9), utm_crs(0.0, 179.99)] == [
        "EPSG:32617",
        "EPSG:32756",
        "EPSG:32631",
        "EPSG:32660",
    ]


def test_a_site_s_mics_table_in_latitude_longitude_places_the_site_and_its_map(compose_cfg, tmp_path):
    from acoustlab.stages.sites import site_from_config, site_map_projection

    gps_table().to_csv(tmp_path / "mics.csv", index=False)
    cfg = compose_cfg(["+site=from_csv", f"site.mics_csv={tmp_path / 'mics.csv'}"])
    site = site_from_config(cfg.site)
    expected = with_map_coordinates(gps_table(), "mics.csv")[["x_m", "y_m"]].to_numpy(float)
    np.testing.assert_allclose(site.mic_positions_m[:, :2], expected)
    _, translation, crs, geographic = site_map_projection(cfg.site)
    assert crs == "EPSG:32617" and geographic and 400_000 < translation[0] < 500_000
    assert site_map_projection(compose_cfg(["+site=from_csv"]).site) is None  # the example's mics: a local frame only
