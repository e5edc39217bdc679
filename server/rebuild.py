"""``hybridloc map rebuild --site S``: a radio map from the surveys stored in the database.

A survey is a device's steps, scans and survey marks, read through the store's walks
(:meth:`Store.read_walk`). For each device of the site that sent at least two marks, its scans are
labelled by the PDR bridged between consecutive marks (:func:`hybridloc.radio.survey.label_scans`, the
same passive-survey labelling as ``map build``), and the labelled scans of all devices build the site's
new radio map version.

Incremental and resumable: each device's labelled scans are cached in ``<cache>/<site>/<device>.json``
together with the device's last batch sequence number; a device whose data did not change since is
not labelled again, and a rebuild interrupted half-way resumes with the devices already done.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from hybridloc.radio.radiomap import BuildParams, build_radio_map
from hybridloc.radio.survey import LabelledScan, label_scans
from hybridloc.types import RfScan, Technology, Waypoints

from . import db as m
from .store import Store


def _device_survey(store: Store, site: str, device: str):
    """(steps, survey marks, WiFi scans) of all the device's stored walks, each sorted by time."""
    walks = [store.read_walk(w.walk_id) for w in store.walks(site, device=device)]
    steps = sorted((st for w in walks for st in w.steps), key=lambda st: st.t)
    marks = sorted((mk for w in walks for mk in w.marks), key=lambda mk: mk.t)
    scans = sorted((sc for w in walks for sc in w.scans if sc.technology == Technology.WIFI), key=lambda sc: sc.t)
    return steps, marks, scans


def rebuild(store: Store, site: str, cache_dir: str | os.PathLike, progress=None) -> tuple[int | None, int, int]:
    """(new map version or None, labelled scans, devices relabelled)."""
    cache = Path(cache_dir) / site
    cache.mkdir(parents=True, exist_ok=True)
    labelled: list[LabelledScan] = []
    relabelled = 0
    with Session(store.engine) as s:
        devices = s.execute(select(m.Device).where(m.Device.site_id == site).order_by(m.Device.id)).scalars().all()
        for i, dev in enumerate(devices, 1):
            f = cache / f"{dev.id}.json"
            cached = None
            if f.is_file():
                try:
                    cached = json.loads(f.read_text())
                except ValueError:
                    cached = None
            if cached is None or cached.get("last_seq") != dev.last_seq:
                steps, marks, scans = _device_survey(store, site, dev.id)
                rows = []
                by_floor: dict[str, list] = {}
                for mk in marks:
                    by_floor.setdefault(mk.floor, []).append(mk)
                if len(marks) >= 2 and steps:
                    # marks of one floor at a time (a survey walk changing floor is split there)
                    for floor, mks in by_floor.items():
                        if len(mks) < 2:
                            continue
                        wp = Waypoints(np.array([k.t for k in mks]), np.array([[k.x, k.y] for k in mks]), floor)
                        for ls in label_scans(scans, steps, wp, steps[0].t - 1.0, source=dev.id):
                            rows.append(
                                {
                                    "t": ls.scan.t,
                                    "x": float(ls.pos_enu[0]),
                                    "y": float(ls.pos_enu[1]),
                                    "sigma": ls.sigma,
                                    "floor": floor,
                                    "rssi": dict(ls.scan.rssi_dbm),
                                    "age": dict(ls.scan.age_s),
                                }
                            )
                tmp = f.with_suffix(".tmp")
                tmp.write_text(json.dumps({"last_seq": dev.last_seq, "model": dev.model, "scans": rows}))
                os.replace(tmp, f)
                cached = json.loads(f.read_text())
                relabelled += 1
            for r in cached["scans"]:
                labelled.append(
                    LabelledScan(
                        RfScan(r["t"], "wifi", r["rssi"], age_s=r.get("age", {}), device_model=cached.get("model", "")),
                        np.array([r["x"], r["y"]]),
                        r["sigma"],
                        r["floor"],
                        dev.id,
                    )
                )
            if progress:
                progress(i, len(devices), dev.id)
    if not labelled:
        return None, 0, relabelled
    rmap = build_radio_map(labelled, site=site, params=BuildParams(max_age_s=8.0))
    tmpf = Path(cache) / "map.tmp.npz"
    rmap.save(tmpf)
    data = tmpf.read_bytes()
    tmpf.unlink()
    survey_devices = sorted({ls.source for ls in labelled})
    return store.save_map(site, data, len(labelled), source="survey", provenance={"survey_devices": survey_devices}), len(labelled), relabelled
