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
import uuid
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


def label_device(device: str, steps, marks, scans) -> list[dict]:
    """A device's labelled scans as cache rows (pure: no database; a Dask task under ``--scheduler``):
    the scans labelled by the PDR bridged between consecutive marks of one floor at a time (a survey
    walk changing floor is split there); none without two marks and a step. On one BLAS thread
    wherever it runs (a result must not depend on the thread count: server/slam_batch.py, solve_floor)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        return _label_rows(device, steps, marks, scans)


def _label_rows(device: str, steps, marks, scans) -> list[dict]:
    rows: list[dict] = []
    by_floor: dict[str, list] = {}
    for mk in marks:
        by_floor.setdefault(mk.floor, []).append(mk)
    if len(marks) >= 2 and steps:
        for floor, mks in by_floor.items():
            if len(mks) < 2:
                continue
            wp = Waypoints(np.array([k.t for k in mks]), np.array([[k.x, k.y] for k in mks]), floor)
            for ls in label_scans(scans, steps, wp, steps[0].t - 1.0, source=device):
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
    return rows


def _label_task(device: str, survey: tuple) -> list[dict]:
    return label_device(device, *survey)


def map_bytes(labelled: list[LabelledScan], site: str) -> bytes:
    """The radio map of the labelled scans, as the bytes stored (pure; a Dask task with a client)."""
    import tempfile

    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):  # as label_device
        rmap = build_radio_map(labelled, site=site, params=BuildParams(max_age_s=8.0))
    with tempfile.TemporaryDirectory(prefix="hybridloc-map-") as d:
        tmpf = Path(d) / "map.npz"
        rmap.save(tmpf)
        return tmpf.read_bytes()


def _read_cache(f: Path) -> dict | None:
    if not f.is_file():
        return None
    try:
        return json.loads(f.read_text())
    except ValueError:
        return None


def _write_cache(f: Path, last_seq, model: str, rows: list[dict]) -> None:
    tmp = f.with_suffix(".tmp")
    tmp.write_text(json.dumps({"last_seq": last_seq, "model": model, "scans": rows}))
    os.replace(tmp, f)


def rebuild(store: Store, site: str, cache_dir: str | os.PathLike, progress=None, client=None) -> tuple[int | None, int, int]:
    """(new map version or None, labelled scans, devices relabelled).

    ``client``: a :class:`distributed.Client`: each device to relabel is a Dask task
    (:func:`label_device`), and the map another (:func:`map_bytes`); this process reads the surveys,
    writes each device's cache file as its task returns (so an interrupted rebuild resumes with them)
    and stores the map. The result equals the serial path's: the same functions on the same input,
    the map built from the cache files' rows in device order either way."""
    cache = Path(cache_dir) / site
    cache.mkdir(parents=True, exist_ok=True)
    relabelled = 0
    with Session(store.engine) as s:
        devices = s.execute(select(m.Device).where(m.Device.site_id == site).order_by(m.Device.id)).scalars().all()
        devices = [(d.id, d.last_seq, d.model) for d in devices]
    stale = [(dev, seq, model) for dev, seq, model in devices if (c := _read_cache(cache / f"{dev}.json")) is None or c.get("last_seq") != seq]
    done = len(devices) - len(stale)
    if client is None:
        for i, (dev, seq, model) in enumerate(devices, 1):
            if (dev, seq, model) in stale:
                _write_cache(cache / f"{dev}.json", seq, model, label_device(dev, *_device_survey(store, site, dev)))
                relabelled += 1
            if progress:
                progress(i, len(devices), dev)
    else:
        from distributed import as_completed

        tag = uuid.uuid4().hex[:8]  # keys of this call only (a shared scheduler may run others)
        futures = {}
        for dev, seq, model in stale:
            (survey,) = client.scatter([_device_survey(store, site, dev)], hash=False)
            fut = client.submit(_label_task, dev, survey, key=f"hybridloc-label-{site}-{dev}-{tag}", pure=False)
            futures[fut] = (dev, seq, model, survey)
        if progress and done:
            progress(done, len(devices), "cached")
        try:
            for fut in as_completed(list(futures)):
                dev, seq, model, _ = futures[fut]
                _write_cache(cache / f"{dev}.json", seq, model, fut.result())
                relabelled += 1
                done += 1
                if progress:
                    progress(done, len(devices), dev)
        finally:
            pending = [f for f in futures if not f.done()]  # an error or an interrupt: stop the rest
            if pending:
                client.cancel(pending)
    labelled: list[LabelledScan] = []
    for dev, _, _ in devices:
        cached = json.loads((cache / f"{dev}.json").read_text())
        for r in cached["scans"]:
            labelled.append(
                LabelledScan(
                    RfScan(r["t"], "wifi", r["rssi"], age_s=r.get("age", {}), device_model=cached.get("model", "")),
                    np.array([r["x"], r["y"]]),
                    r["sigma"],
                    r["floor"],
                    dev,
                )
            )
    if not labelled:
        return None, 0, relabelled
    if client is None:
        data = map_bytes(labelled, site)
    else:
        (lab,) = client.scatter([labelled], hash=False)
        data = client.submit(map_bytes, lab, site, key=f"hybridloc-map-{site}-{uuid.uuid4().hex[:8]}", pure=False).result()
    survey_devices = sorted({ls.source for ls in labelled})
    return store.save_map(site, data, len(labelled), source="survey", provenance={"survey_devices": survey_devices}), len(labelled), relabelled
