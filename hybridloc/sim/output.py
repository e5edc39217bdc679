"""Writing simulated worlds and walks in the real data formats.

World folder (``hybridloc sim world``): ``world.json`` (seed, floors, size, infrastructure, origin),
and per floor ``F<n>/geojson_map.json`` + ``F<n>/floor_info.json`` in the Indoor Location Competition
layout, so :func:`hybridloc.io.msft.read_ilc_site` and every command reading ILC floor plans accept it,
plus ``floorplan.geojson`` (WGS84) for GIS tools.

Walk folder (``hybridloc sim walk``), per walker ``w<NNNN>``:

* ``w<NNNN>.txt.gz``: the phone in the Indoor Location Competition trace format (accelerometer,
  gyroscope, magnetometer in uT, Android's rotation vector as real phones log it, WiFi, iBeacon; waypoints = true positions at route corners and
  pauses, marked like an operator would, each with its floor name as an extra field). The header's
  FloorName is the start floor (the format has one floor per trace; ``truth_steps.csv`` has the floor
  of every step);
* ``w<NNNN>_foot.csv``: the foot IMU in the plain IMU CSV (when the carrier includes a foot unit);
* ``w<NNNN>_truth_steps.csv``: ``t,x,y,z,floor,heading,length,bounce`` of every true step (bounce:
  the centre of mass's vertical excursion over the step, m);
* ``w<NNNN>_truth_foot.csv``: ``t,x,y,z,stance`` of the foot at every IMU sample;
* ``w<NNNN>_fixes.csv``: ``t,x,y,floor,sigma,source,sigma_random`` of simulated GPS and RFID fixes
  (:func:`hybridloc.io.fixes.read_fixes_csv`; ``sigma_random``: the GPS fix's random part, for the
  differential mode);
* ``w<NNNN>.json``: walker parameters and route facts (loop, outdoor start).
"""

from __future__ import annotations

import csv
import gzip
import io
import json
import math
import os
from pathlib import Path

import numpy as np
from shapely.geometry import LineString, mapping

from ..io.imu_files import write_imu_csv
from ..io.writers import floorplan_features, write_geojson
from ..units import DEG
from .building import STOREY, World
from .imu import FootTruth
from .radio import WalkRadio
from .walker import Walk


def world_to_json(world: World) -> dict:
    return {
        "format": "hybridloc-sim-world",
        "version": 1,
        "seed": world.seed,
        "floors": world.n_floors,
        "width": world.width,
        "depth": world.depth,
        "floorplan": world.source,
        "origin_deg": [world.origin.lat / DEG, world.origin.lon / DEG, world.origin.height],
        "aps": [
            {"id": i, "x": float(p[0]), "y": float(p[1]), "floor": world.floor_name(int(p[2])), "freq_mhz": float(f)}
            for i, p, f in zip(world.ap_ids, world.aps, world.ap_freq_mhz)
        ],
        "beacons": [
            {"id": i, "x": float(p[0]), "y": float(p[1]), "floor": world.floor_name(int(p[2]))} for i, p in zip(world.beacon_ids, world.beacons)
        ],
        "rfid_readers": [{"x": float(p[0]), "y": float(p[1]), "floor": world.floor_name(int(p[2]))} for p in world.rfid],
        "rooms": [{"name": r.name, "floor": world.floor_name(r.floor), "door": list(r.door)} for r in world.rooms],
    }


def write_world(world: World, out: str | os.PathLike) -> None:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "world.json").write_text(json.dumps(world_to_json(world), indent=1), encoding="utf-8")
    write_geojson(out / "floorplan.geojson", floorplan_features(world.plan, world.origin), world.origin)
    o = world.origin
    for fl in world.plan.floors:
        d = out / fl.name
        d.mkdir(exist_ok=True)
        feats = [
            {
                "type": "Feature",
                "geometry": mapping(_to_lonlat(fl.outline, o)),
                "properties": {"category": "floor", "name": fl.name, "floor_num": fl.level + 1, "type": "floor"},
            }
        ]
        for name, poly in fl.rooms:
            feats.append({"type": "Feature", "geometry": mapping(_to_lonlat(poly, o)), "properties": {"name": name, "category": ["room"]}})
        # the walls themselves, doors and entrances left open (our extension of the format: the ILC
        # plans carry only outlines; read_ilc_floor takes these in place of the outline's boundary)
        for a, b in fl.walls:
            feats.append({"type": "Feature", "geometry": mapping(_to_lonlat(LineString([a, b]), o)), "properties": {"category": "wall"}})
        (d / "geojson_map.json").write_text(json.dumps({"type": "FeatureCollection", "features": feats}), encoding="utf-8")
        x0, y0, x1, y1 = fl.outline.bounds
        (d / "floor_info.json").write_text(json.dumps({"map_info": {"height": y1 - y0, "width": x1 - x0}}), encoding="utf-8")


def _to_lonlat(geom, origin):
    import shapely

    def f(xy):
        lat, lon, _ = origin.enu_to_geodetic(xy)
        return np.column_stack([lon / DEG, lat / DEG])

    return shapely.transform(geom, f)


def waypoints(walk: Walk) -> list[tuple[float, float, float, int]]:
    """True positions an operator would mark: at the start, at every turn and pause, and at the end;
    (t, x, y, floor index) each."""
    out = [(walk.t0, walk.start[0], walk.start[1], int(walk.start[2]))]
    prev_h = None
    for s in walk.steps:
        if prev_h is not None and abs(math.atan2(math.sin(s.heading - prev_h), math.cos(s.heading - prev_h))) > 20 * DEG:
            out.append((s.t, s.x, s.y, int(s.floor)))
        prev_h = s.heading
    for a, _, _ in walk.pauses[1:]:
        pos, floor = walk.position_at(np.array([a]))
        out.append((a, float(pos[0, 0]), float(pos[0, 1]), int(floor[0])))
    if walk.steps:
        out.append((walk.steps[-1].t, walk.steps[-1].x, walk.steps[-1].y, int(walk.steps[-1].floor)))
    out.sort()
    dedup = [out[0]]
    for w in out[1:]:
        if w[0] - dedup[-1][0] > 0.5:
            dedup.append(w)
    return dedup


def write_ilc_trace(
    path: str | os.PathLike, world: World, walk: Walk, imu, radio: WalkRadio, device_model: str = "SIM PHONE", rotation_vector=None
) -> None:
    """The phone's trace; ``rotation_vector`` (t, quaternions w x y z, :func:`.imu.phone_sensors`) adds
    TYPE_ROTATION_VECTOR lines ``x y z 3`` as ILC phones log them (accuracy 3, high; w >= 0 implied)."""
    ms = lambda t: int(round(t * 1000))  # noqa: E731
    lines: list[tuple[int, float, str]] = []
    brand, _, model = device_model.partition(" ")
    mag = imu.mag_body * 1e6
    for i in range(len(imu)):
        tm = ms(imu.t[i])
        a, g, m = imu.accel_body[i], imu.gyro_body[i], mag[i]
        lines.append((tm, 0, f"{tm}\tTYPE_ACCELEROMETER\t{a[0]:.6f}\t{a[1]:.6f}\t{a[2]:.6f}\t3"))
        lines.append((tm, 1, f"{tm}\tTYPE_GYROSCOPE\t{g[0]:.6f}\t{g[1]:.6f}\t{g[2]:.6f}\t3"))
        lines.append((tm, 2, f"{tm}\tTYPE_MAGNETIC_FIELD\t{m[0]:.4f}\t{m[1]:.4f}\t{m[2]:.4f}\t3"))
    if rotation_vector is not None:
        for tr, q in zip(rotation_vector[0].tolist(), rotation_vector[1][:, 1:].tolist()):
            tm = ms(tr)
            lines.append((tm, 2.5, f"{tm}\tTYPE_ROTATION_VECTOR\t{q[0]:.8f}\t{q[1]:.8f}\t{q[2]:.8f}\t3"))
    for s in radio.wifi:
        tm = ms(s.t)
        for k, r in s.rssi_dbm.items():
            last = ms(s.t - s.age_s.get(k, 0.0))
            lines.append((tm, 3, f"{tm}\tTYPE_WIFI\tsim\t{k}\t{int(r)}\t{int(s.frequency_hz.get(k, 2.437e9) / 1e6)}\t{last}"))
    for s in radio.ble:
        tm = ms(s.t)
        for k, r in s.rssi_dbm.items():
            uuid, major, minor = k.split("_")
            lines.append(
                (
                    tm,
                    4,
                    f"{tm}\tTYPE_BEACON\t{uuid.upper()}\t{major}\t{minor}\t-59\t{int(r)}\t{10 ** ((-59 - r) / 20):.3f}\tSIM:{major}:{minor}\t{tm}",
                )
            )
    for t, x, y, floor in waypoints(walk):  # each mark with its floor (the format's extension): walks take the stairs
        lines.append((ms(t), 5, f"{ms(t)}\tTYPE_WAYPOINT\t{x:.4f}\t{y:.4f}\t{world.floor_name(floor)}"))
    lines.sort(key=lambda r: (r[0], r[1]))
    fl = world.floor_name(walk.start[2])
    # mtime=0: the same walk gives the same bytes (gzip otherwise stamps the wall-clock time in its header)
    with io.TextIOWrapper(gzip.GzipFile(path, "wb", compresslevel=3, mtime=0), encoding="utf-8") as f:
        f.write(f"#\tstartTime:{ms(walk.t0)}\n#\tSiteID:sim-{world.seed}\tSiteName:simulated building {world.seed}\tFloorId:{fl}\tFloorName:{fl}\n")
        f.write(f"#\tBrand:{brand}\tModel:{model}\tAndroidName:sim\tAPILevel:0\n")
        # the sensors' full scale, as Android reports it (type 1 accelerometer, 4 gyroscope)
        for typ, name, full in ((1, "Accelerometer", imu.accel_range), (4, "Gyroscope", imu.gyro_range)):
            if full is not None:
                f.write(f"#\ttype:{typ}\tname:SIM {name}\tvendor:hybridloc\tmaximumRange:{full:.6f}\n")
        f.write("\n".join(r[2] for r in lines))
        f.write(f"\n#\tendTime:{ms(walk.t1)}\n")


def write_truth(prefix: Path, walk: Walk, radio: WalkRadio | None, foot: FootTruth | None, world: World) -> None:
    with open(f"{prefix}_truth_steps.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "x", "y", "z", "floor", "heading", "length", "bounce"])
        z = walk.start[2] * STOREY
        for s in walk.steps:
            z += s.dz
            w.writerow(
                [
                    f"{s.t:.3f}",
                    f"{s.x:.4f}",
                    f"{s.y:.4f}",
                    f"{z:.3f}",
                    world.floor_name(s.floor),
                    f"{s.heading:.6f}",
                    f"{s.length:.4f}",
                    f"{s.bounce:.5f}",
                ]
            )
    if foot is not None:
        with open(f"{prefix}_truth_foot.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t", "x", "y", "z", "stance"])
            for i in range(len(foot.t)):
                w.writerow([f"{foot.t[i]:.5f}", f"{foot.pos[i, 0]:.5f}", f"{foot.pos[i, 1]:.5f}", f"{foot.pos[i, 2]:.5f}", int(foot.stance[i])])
    if radio is not None:
        with open(f"{prefix}_fixes.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["t", "x", "y", "floor", "sigma", "source", "sigma_random"])
            rows = [(fx, sr) for fx, sr in zip(radio.gps, radio.gps_sigma_random or [None] * len(radio.gps))] + [(fx, None) for fx in radio.rfid]
            for fx, sr in sorted(rows, key=lambda a: a[0].t):
                w.writerow(
                    [
                        f"{fx.t:.3f}",
                        f"{fx.pos_enu[0]:.3f}",
                        f"{fx.pos_enu[1]:.3f}",
                        fx.floor or "",
                        f"{math.sqrt(fx.cov[0, 0]):.3f}",
                        fx.source.value,
                        "" if sr is None else f"{sr:.3f}",
                    ]
                )
    meta = {
        "walker": walk.walker,
        "speed": walk.speed,
        "step_length": walk.step_length,
        "length_k": walk.length_k,
        "leg_length": walk.leg_length,
        "pendulum_correction": walk.pendulum_correction,
        "t0": walk.t0,
        "t1": walk.t1,
        "loop": walk.loop,
        "outdoor_start": walk.outdoor_start,
        "n_steps": len(walk.steps),
        "start": list(walk.start),
        "pauses": [list(p) for p in walk.pauses],
    }
    Path(f"{prefix}.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")


def write_foot_csv(prefix: Path, imu) -> None:
    write_imu_csv(f"{prefix}_foot.csv", imu)
