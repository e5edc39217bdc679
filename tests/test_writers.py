import json
import math

import numpy as np
import pytest
from shapely.geometry import Polygon

from hybridloc.geo import GeodeticOrigin
from hybridloc.io.writers import (
    floorplan_features,
    hdt_sentence,
    nmea_checksum,
    nmea_lines,
    parse_nmea_gga,
    read_trajectory_csv,
    region_feature,
    track_feature,
    write_geojson,
    write_nmea,
    write_trajectory_csv,
)
from hybridloc.types import ContainmentRegion, Floor, FloorPlan, Trajectory
from hybridloc.units import DEG


def _traj():
    t = 1574559495.0 + np.arange(5.0)
    return Trajectory(t, np.column_stack([np.arange(5.0), 2 * np.arange(5.0), np.zeros(5)]), ("F1",) * 4 + (None,), np.full((5, 3), 0.5))


def test_trajectory_csv_round_trip(tmp_path):
    p = tmp_path / "traj.csv"
    tr = _traj()
    write_trajectory_csv(p, tr)
    assert p.read_text().splitlines()[0] == "t,x,y,z,floor,sigma_x,sigma_y,sigma_z"
    back = read_trajectory_csv(p)
    np.testing.assert_allclose(back.pos_enu, tr.pos_enu)
    np.testing.assert_allclose(back.t, tr.t, atol=1e-6)
    assert back.floor == tr.floor
    np.testing.assert_allclose(back.sigma_enu, tr.sigma_enu)


def test_nmea_checksum_reference_sentence():
    # The widely quoted reference GGA sentence and its checksum (NMEA-0183 examples).
    assert nmea_checksum("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,") == "47"


def test_nmea_position_round_trip_and_heading(tmp_path):
    o = GeodeticOrigin.from_degrees(30.2925, 120.0742, 10.0)
    tr = _traj()
    lines = nmea_lines(tr, o, heading=[0.0, math.pi / 2, math.pi, -math.pi / 2, 0.1])
    assert len(lines) == 10 and lines[0].startswith("$GNGGA,") and lines[1].startswith("$GNHDT,")
    for i in range(5):
        lat, lon, h = parse_nmea_gga(lines[2 * i])
        back = o.geodetic_to_enu(lat * DEG, lon * DEG, h)
        # 5 decimals of arc-minutes resolve 1e-5' ~ 1.9 cm in latitude and less in longitude.
        np.testing.assert_allclose(back[:2], tr.pos_enu[i, :2], atol=0.02)
    assert hdt_sentence(math.pi / 2).startswith("$GNHDT,0.00,T*")  # heading North = bearing 0
    assert lines[3].startswith("$GNHDT,0.00,T") and lines[1].startswith("$GNHDT,90.00,T")
    p = tmp_path / "x.nmea"
    write_nmea(p, tr, o)
    assert p.read_bytes().count(b"\r\n") == 5
    with pytest.raises(ValueError, match="checksum"):
        parse_nmea_gga(lines[0][:-2] + "00")


def test_geojson_wgs84_and_local(tmp_path):
    o = GeodeticOrigin.from_degrees(30.2925, 120.0742)
    sq = Polygon([(0, 0), (10, 0), (10, 10), (0, 10)])
    fl = Floor("F1", 0, 0.0, sq, sq, np.zeros((0, 2, 2)), (("shop", Polygon([(1, 1), (2, 1), (2, 2)])),))
    plan = FloorPlan("s", (fl,), (), o)
    reg = ContainmentRegion("F1", sq.buffer(-1), 0.95, t=3.0)
    feats = [track_feature(_traj(), o, device="d1"), region_feature(reg, o), *floorplan_features(plan, o)]
    p = tmp_path / "out.geojson"
    write_geojson(p, feats, o)
    fc = json.loads(p.read_text())
    assert fc["type"] == "FeatureCollection" and "crs_note" not in fc
    lon, lat = fc["features"][0]["geometry"]["coordinates"][0]
    assert lon == pytest.approx(120.0742, abs=1e-9) and lat == pytest.approx(30.2925, abs=1e-9)
    assert fc["features"][1]["properties"]["mass"] == 0.95
    assert {f["properties"]["kind"] for f in fc["features"]} == {"track", "containment_region", "floor", "room"}
    p2 = tmp_path / "local.geojson"
    write_geojson(p2, [track_feature(_traj())])
    fc2 = json.loads(p2.read_text())
    assert "crs_note" in fc2 and fc2["features"][0]["geometry"]["coordinates"][1] == [1.0, 2.0]
