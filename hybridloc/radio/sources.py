"""Turning input files into labelled scans (for ``map build``) and scans to locate (``locate``).

Formats:

* ``msft``: Indoor Location Competition traces (files, floor folders or site folders). For building,
  every trace is a passive survey (:mod:`.survey`); the floor plan comes from the site folder's
  ``geojson_map.json`` files unless ``--floorplan`` names one.
* ``ujiindoorloc``: UJIIndoorLoc CSV rows; position = (LONGITUDE, LATITUDE) metres (EPSG:3857),
  floor named ``b<building>_f<floor>`` inside the map; ``locate`` writes the plain floor number and
  the building.
* ``csv``: labelled readings, one per line: ``t,x,y,floor,transmitter,rssi_dbm[,sigma]`` (s, m, m,
  name, id, dBm, m); lines sharing ``t`` (and floor) form one scan. For ``locate`` x, y may be empty.
"""

from __future__ import annotations

import csv
import math
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ..io.common import DataFormatError
from ..io.msft import find_ilc_traces, read_ilc_site, read_ilc_trace
from ..io.uji import read_uji
from ..types import FloorPlan, RfScan, Technology
from .survey import LabelledScan, label_trace

FORMATS = ("msft", "ujiindoorloc", "csv")


def uji_floor_name(building: int, floor: int) -> str:
    return f"b{int(building)}_f{int(floor)}"


def _ilc_paths(inputs: list[str]) -> list[Path]:
    paths: list[Path] = []
    for i in inputs:
        p = Path(i)
        if p.is_dir():
            paths += find_ilc_traces(p)
        elif p.is_file():
            paths.append(p)
        else:
            raise DataFormatError(i, None, "no such file or folder")
    return paths


def _site_dir_of(inputs: list[str]) -> Path | None:
    for i in inputs:
        p = Path(i)
        for cand in [p, *p.parents]:
            if cand.is_dir() and any((d / "geojson_map.json").is_file() for d in cand.iterdir() if d.is_dir()):
                return cand
    return None


def labelled_from_inputs(fmt: str, inputs: list[str], floorplan: str | None = None) -> tuple[list[LabelledScan], FloorPlan | None, str]:
    """(labelled scans, floor plan or None, site name) from the inputs of ``map build``."""
    if fmt == "msft":
        paths = _ilc_paths(inputs)
        out: list[LabelledScan] = []
        site = ""
        for p in paths:
            tr = read_ilc_trace(p)
            site = site or (tr.site or "")
            out += label_trace(tr, source=p.name)
        plan = None
        sd = Path(floorplan) if floorplan else _site_dir_of(inputs)
        if sd is not None:
            plan = read_ilc_site(sd if sd.is_dir() else sd.parent.parent)
        return out, plan, site
    if fmt == "ujiindoorloc":
        out = []
        for i in inputs:
            d = read_uji(i)
            for r in range(len(d)):
                s = d.scan(r)
                if len(s):
                    out.append(LabelledScan(s, d.pos[r].copy(), 1.0, uji_floor_name(d.building[r], d.floor[r]), f"{Path(i).name}:{d.lines[r]}"))
        return out, None, "ujiindoorloc"
    if fmt == "csv":
        out = []
        for i in inputs:
            for scan, xy, floor, sigma in read_scans_csv(i):
                if xy is None:
                    raise DataFormatError(i, None, f"scan at t={scan.t} has no position: map building needs labelled scans")
                out.append(LabelledScan(scan, xy, sigma, floor, Path(i).name))
        return out, None, ""
    raise ValueError(f"unknown format {fmt!r}; choose one of {FORMATS}")


def read_scans_csv(path: str) -> list[tuple[RfScan, np.ndarray | None, str | None, float]]:
    groups: OrderedDict[tuple, dict] = OrderedDict()
    with open(path, newline="", encoding="utf-8") as f:
        rd = csv.DictReader(f)
        need = {"t", "x", "y", "floor", "transmitter", "rssi_dbm"}
        if not rd.fieldnames or not need <= set(rd.fieldnames):
            raise DataFormatError(path, 1, f"scan CSV needs columns {','.join(sorted(need))}[,sigma]")
        for n, row in enumerate(rd, start=2):
            try:
                t = float(row["t"])
                r = float(row["rssi_dbm"])
                x = float(row["x"]) if row["x"] not in ("", None) else None
                y = float(row["y"]) if row["y"] not in ("", None) else None
                sg = float(row["sigma"]) if row.get("sigma") else 1.0
            except ValueError as exc:
                raise DataFormatError(path, n, f"bad number: {exc}") from exc
            if not (math.isfinite(t) and math.isfinite(r)):
                raise DataFormatError(path, n, "non-finite time or RSSI")
            key = (t, row["floor"] or None)
            g = groups.setdefault(key, {"rssi": {}, "xy": None if x is None or y is None else np.array([x, y]), "sigma": sg})
            g["rssi"][row["transmitter"]] = r
    out = []
    for (t, floor), g in groups.items():
        try:
            scan = RfScan(t, "wifi", g["rssi"])
        except ValueError as exc:
            raise DataFormatError(path, None, f"scan at t={t}: {exc}") from exc
        out.append((scan, g["xy"], floor, g["sigma"]))
    return out


def scans_to_locate(fmt: str, path: str) -> tuple[list[RfScan], str | None]:
    """(scans in input order, site id or None when the format does not say) of one ``locate`` input."""
    if fmt == "msft":
        tr = read_ilc_trace(path)
        return [s for s in tr.scans if s.technology is Technology.WIFI], tr.site
    if fmt == "ujiindoorloc":
        d = read_uji(path)
        return [d.scan(r) for r in range(len(d))], "ujiindoorloc"
    if fmt == "csv":
        return [r[0] for r in read_scans_csv(path)], None
    raise ValueError(f"unknown format {fmt!r}; choose one of {FORMATS}")
