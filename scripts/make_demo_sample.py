"""Rebuild the bundled demo sample (hybridloc/data/ilc_site1_F1) from the full Indoor Location
Competition site1 floor F1.

    python scripts/make_demo_sample.py ../shared/data/msft-ilc/site1 [--budget-mb 6.5]

What it does, so the sample's provenance is reproducible:

* **Clients**: the four walks with the longest waypoint path. The demo replays them as phone clients;
  fusion matters as PDR drifts, which short walks do not show.
* **Surveys**: from the other walks, greedily the one that adds the most newly covered 4 m cells along
  waypoint paths (the clients' paths weigh double: the map must cover where clients walk) per byte,
  until the byte budget is spent. Waypoint paths are the surveys' own labels; nothing of the clients'
  recordings other than their waypoints guides the choice.
* **Stripping**: record types the reader documents as unused (``hybridloc.io.msft.UNUSED_TYPES``: the
  uncalibrated sensor streams, raw BLE advertisements) are removed; every other line is kept byte for
  byte. The floor plan files and the licence are copied unchanged. Gzip with mtime 0 (reproducible).
"""

from __future__ import annotations

import argparse
import gzip
import io
import math
import shutil
from pathlib import Path

import numpy as np

from hybridloc.io.msft import UNUSED_TYPES, read_ilc_trace

CELL_M = 4.0
N_CLIENTS = 4
CLIENT_WEIGHT = 2.0  # weight of cells on the clients' routes (an operator surveys where the public walks; 1: the floor alone)


def path_cells(wxy: np.ndarray) -> set[tuple[int, int]]:
    cells = set()
    for a, b in zip(wxy[:-1], wxy[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a))))
        for u in np.linspace(0.0, 1.0, n + 1):
            p = a + u * (b - a)
            cells.add((int(p[0] // CELL_M), int(p[1] // CELL_M)))
    return cells


def stripped(path: Path) -> bytes:
    keep = []
    with gzip.open(path, "rb") as f:
        for line in f:
            parts = line.split(b"\t", 2)
            if len(parts) > 1 and parts[1].strip().decode("ascii", "replace") in UNUSED_TYPES:
                continue
            keep.append(line)
    buf = io.BytesIO()
    with gzip.GzipFile(fileobj=buf, mode="wb", mtime=0, compresslevel=9) as g:
        g.write(b"".join(keep))
    return buf.getvalue()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("site", help="Indoor Location Competition site1 folder (with F1/)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "hybridloc" / "data" / "ilc_site1_F1"))
    ap.add_argument("--budget-mb", type=float, default=6.5, help="bytes of traces to ship, MB")
    args = ap.parse_args()
    src = Path(args.site)
    files = sorted((src / "F1" / "path_data_files").glob("*.txt.gz"))
    walks = {}
    for p in files:
        tr = read_ilc_trace(p)
        if tr.imu is None or len(tr.waypoints) < 2:
            continue
        wxy = tr.waypoints.pos_enu
        walks[p] = (float(np.linalg.norm(np.diff(wxy, axis=0), axis=1).sum()), path_cells(wxy))
    clients = sorted(walks, key=lambda p: -walks[p][0])[:N_CLIENTS]
    data = {p: stripped(p) for p in walks}
    budget = args.budget_mb * 1e6 - sum(len(data[p]) for p in clients)
    want = {c: CLIENT_WEIGHT for p in clients for c in walks[p][1]}
    covered: set = set()
    surveys: list[Path] = []
    rest = [p for p in walks if p not in clients]
    while rest:
        gain = [(sum(want.get(c, 1.0) for c in walks[p][1] - covered) / len(data[p]), p) for p in rest]
        g, best = max(gain)
        if g <= 0 or len(data[best]) > budget:
            rest.remove(best)
            continue
        surveys.append(best)
        covered |= walks[best][1]
        budget -= len(data[best])
        rest.remove(best)
    out = Path(args.out)
    dst = out / "F1" / "path_data_files"
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for p in clients + surveys:
        (dst / p.name).write_bytes(data[p])
    copies = [(src / "F1" / n, out / "F1" / n) for n in ("geojson_map.json", "floor_info.json")] + [(src.parent / "LICENSE", out / "LICENSE")]
    for a, b in copies:
        if a.is_file():
            b.unlink(missing_ok=True)
            shutil.copyfile(a, b)
    (out / "clients.txt").write_text("".join(f"{p.name}\n" for p in clients))
    client_cells = set().union(*(walks[p][1] for p in clients))
    print(
        f"{len(clients)} clients ({sum(walks[p][0] for p in clients):.0f} m of waypoint path), {len(surveys)} surveys; "
        f"{sum(len(data[p]) for p in clients + surveys) / 1e6:.2f} MB; clients' cells covered by surveys "
        f"{100 * len(client_cells & covered) / len(client_cells):.0f} %"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
