"""``hybridloc floorplan import`` and ``floorplan export``: floor plans in the server's database."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import MissingData
from ._common import check_db_driver


def _read_plan(path: str):
    """A site folder of Indoor Location Competition floor folders, or a hybridloc floor-plan GeoJSON file."""
    from ..io.floorplan_geojson import floorplan_from_geojson
    from ..io.msft import read_ilc_site

    p = Path(path)
    if p.is_dir():
        return read_ilc_site(p)
    if p.is_file():
        return floorplan_from_geojson(p.read_bytes(), source=str(p))
    raise MissingData(f"{p}: no such file or folder")


def _cmd_floorplan_import(args: argparse.Namespace) -> int:
    check_db_driver(args.db)
    from ..server.store import Store

    plan = _read_plan(args.source)
    site = args.site or plan.site
    st = Store(args.db)
    try:
        before = st.floor_plan_version(site)
        row = st.save_floor_plan(site, plan)
    finally:
        st.close()
    fl = ", ".join(f"{f.name} (level {f.level}, {len(f.walls)} walls, walkable {f.walkable.area:.0f} m^2)" for f in plan.floors)
    same = " (unchanged: the site's newest plan is this one)" if row == before else ""
    print(f"{args.source} -> site {site} floor plan {row}{same} in {args.db}: {fl}")
    return 0


def _cmd_floorplan_export(args: argparse.Namespace) -> int:
    check_db_driver(args.db)
    from ..io.floorplan_geojson import floorplan_to_geojson
    from ..server.store import Store

    st = Store(args.db)
    try:
        plan = st.load_floor_plan(args.site)
    finally:
        st.close()
    if plan is None:
        raise MissingData(f"no floor plan for site {args.site!r} in {args.db}")
    Path(args.out).write_text(floorplan_to_geojson(plan), encoding="utf-8")
    print(f"site {args.site} floor plan ({len(plan.floors)} floors) -> {args.out}")
    return 0


def register(sub) -> None:
    fp = sub.add_parser("floorplan", help="floor plans in the server database: import, export")
    fsub = fp.add_subparsers(dest="floorplan_command", required=True)
    fi = fsub.add_parser("import", help="store a site's floor plan (a site folder of floor folders, or a hybridloc floor-plan GeoJSON)")
    fi.add_argument("source", metavar="SITE_DIR", help="site folder (Indoor Location Competition layout) or floor-plan GeoJSON file")
    fi.add_argument("--site", help="site id on the server (default: the settings' site, else the plan's own name)")
    fi.add_argument("--db", help="database file or URL (default hybridloc.db)")
    fi.set_defaults(func=_cmd_floorplan_import, _settings={"site": "site", "db": "db"})
    fe = fsub.add_parser("export", help="write the site's newest floor plan from the server database as GeoJSON (site frame, m)")
    fe.add_argument("--site")
    fe.add_argument("--db")
    fe.add_argument("--out", required=True, metavar="GEOJSON")
    fe.set_defaults(func=_cmd_floorplan_export, _parser=fe, _required=("site",), _settings={"site": "site", "db": "db"})
