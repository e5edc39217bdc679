"""Floor plans in the server database: the GeoJSON codec round trip, the store's floor_plan table (real
SQLite, real migrations), and ``hybridloc floorplan import/export``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hybridloc.io.common import DataFormatError
from hybridloc.io.floorplan_geojson import floorplan_from_geojson, floorplan_to_geojson
from hybridloc.io.msft import read_ilc_site
from hybridloc.samples import ILC_SITE1_F1


def _assert_same_plan(a, b):
    assert a.site == b.site
    assert [f.name for f in a.floors] == [f.name for f in b.floors]
    for fa, fb in zip(a.floors, b.floors):
        assert (fa.level, fa.height) == (fb.level, fb.height)
        # JSON keeps doubles exactly (repr round trip): the geometry is the same to the last bit
        assert fa.outline.equals_exact(fb.outline, 0.0)
        assert fa.walkable.equals_exact(fb.walkable, 0.0)
        np.testing.assert_array_equal(fa.walls, fb.walls)
        assert [n for n, _ in fa.rooms] == [n for n, _ in fb.rooms]
        assert all(pa.equals_exact(pb, 0.0) for (_, pa), (_, pb) in zip(fa.rooms, fb.rooms))
    assert [(t.kind, t.floor_from, t.floor_to, t.pos_from, t.pos_to) for t in a.transitions] == [
        (t.kind, t.floor_from, t.floor_to, tuple(t.pos_from), tuple(t.pos_to)) for t in b.transitions
    ]
    if a.origin is None:
        assert b.origin is None
    else:
        assert math.isclose(a.origin.lat, b.origin.lat, abs_tol=1e-15) and math.isclose(a.origin.lon, b.origin.lon, abs_tol=1e-15)


def test_ilc_plan_round_trips():
    plan = read_ilc_site(ILC_SITE1_F1)
    _assert_same_plan(plan, floorplan_from_geojson(floorplan_to_geojson(plan)))


def test_generated_plan_with_stairs_round_trips():
    from hybridloc.sim.building import generate_world

    plan = generate_world(np.random.default_rng(4), floors=2, seed=4).plan
    back = floorplan_from_geojson(floorplan_to_geojson(plan))
    _assert_same_plan(plan, back)


@pytest.mark.parametrize(
    "text",
    [
        "",
        "not json",
        json.dumps({"type": "FeatureCollection", "features": []}),
        json.dumps({"type": "FeatureCollection", "hybridloc": {"format": "other"}, "features": []}),
        json.dumps({"type": "FeatureCollection", "hybridloc": {"format": "hybridloc-floorplan", "version": 99}, "features": []}),
        json.dumps({"type": "FeatureCollection", "hybridloc": {"format": "hybridloc-floorplan", "version": 1}, "features": []}),
        json.dumps(
            {
                "type": "FeatureCollection",
                "hybridloc": {"format": "hybridloc-floorplan", "version": 1},
                "features": [
                    {"type": "Feature", "geometry": {"type": "Point", "coordinates": [0, 0]}, "properties": {"floor": "F1", "category": "room"}}
                ],
            }
        ),
    ],
)
def test_bad_documents_are_refused(text):
    with pytest.raises(DataFormatError):
        floorplan_from_geojson(text)


def test_store_keeps_plans_by_site(db_url):
    from sqlalchemy import select
    from sqlalchemy.orm import Session

    from hybridloc.server import db as m
    from hybridloc.server.store import Store

    plan = read_ilc_site(ILC_SITE1_F1)
    st = Store(db_url)  # on SQLite and on PostgreSQL
    try:
        assert st.load_floor_plan("s") is None
        first = st.save_floor_plan("s", plan)
        second = st.save_floor_plan("s", plan)
        assert second == first  # the same plan again: no new version
        _assert_same_plan(plan, st.load_floor_plan("s"))
        assert st.load_floor_plan("other") is None
        with Session(st.engine) as s:
            floors = s.execute(select(m.Floor).where(m.Floor.site_id == "s")).scalars().all()
            assert [(f.name, f.level) for f in floors] == [(f.name, f.level) for f in plan.floors]  # once, though saved twice
            site = s.get(m.Site, "s")
            assert math.isclose(site.origin_lat_deg, math.degrees(plan.origin.lat))
    finally:
        st.close()


def test_floorplan_commands(tmp_path):
    from hybridloc.cli import main
    from hybridloc.server.store import Store

    dbf = str(tmp_path / "h.db")
    assert main(["floorplan", "import", str(ILC_SITE1_F1), "--site", "mall", "--db", dbf]) == 0
    out = tmp_path / "plan.geojson"
    assert main(["floorplan", "export", "--site", "mall", "--db", dbf, "--out", str(out)]) == 0
    assert main(["floorplan", "import", str(out), "--site", "copy", "--db", dbf]) == 0
    st = Store(dbf)
    try:
        _assert_same_plan(st.load_floor_plan("mall"), st.load_floor_plan("copy"))
    finally:
        st.close()
    assert main(["floorplan", "export", "--site", "nobody", "--db", dbf, "--out", str(out)]) == 2


def test_the_same_plan_imported_again_adds_no_version(tmp_path, capsys):
    """An import run twice (an operator's script) keeps one version; a changed plan is a new one."""
    from hybridloc.cli import main
    from hybridloc.io.msft import read_ilc_site
    from hybridloc.server.store import Store

    dbf = str(tmp_path / "h.db")
    assert main(["floorplan", "import", str(ILC_SITE1_F1), "--site", "mall", "--db", dbf]) == 0
    assert main(["floorplan", "import", str(ILC_SITE1_F1), "--site", "mall", "--db", dbf]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert "floor plan 1 in" in printed[0] and "floor plan 1 (unchanged" in printed[1]
    st = Store(dbf)
    try:
        assert st.floor_plan_version("mall") == 1
        import dataclasses

        plan = read_ilc_site(ILC_SITE1_F1)
        plan = dataclasses.replace(plan, floors=[dataclasses.replace(plan.floors[0], level=plan.floors[0].level + 1), *plan.floors[1:]])
        # a changed plan: a new version, then the same again: none
        assert st.save_floor_plan("mall", plan) == 2 and st.save_floor_plan("mall", plan) == 2
        assert st.load_floor_plan("mall").floors[0].level == plan.floors[0].level
        assert st.floor_plan_version("nobody") is None
    finally:
        st.close()
