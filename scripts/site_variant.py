"""A variant of an Indoor Location Competition site, to check that the eval commands do not depend on
how the shared site is laid out (issues #21, #24: their figures are measured again on another mall).

    python scripts/site_variant.py SITE_DIR OUT_DIR [--rename F1=B1,F2=F1,F3=F2] [--keep F3=5]
                                   [--plan-only F4,F5]

* ``--rename OLD=NEW,...``: a floor renamed everywhere it is named - its folder, its plan's floor
  feature and its traces' ``FloorName`` header;
* ``--keep FLOOR=N,...``: only the first N traces (by name) of a floor (after renaming: the new name);
* ``--plan-only NAME,...``: extra floors with a plan (a copy of the last floor's) and no traces - the
  first with an empty ``path_data_files``, the others with none.

Traces are copied (gzip kept as it was), never linked. Prints what it wrote; the last line is one JSON
object. The twenty-first session's checks (docs/slam.md, "eval crowd: the measurements"): site1
renamed B1 / F1 / F2 prints the same eval pdr-phone, slam, fusion and fingerprint figures as site1;
``--keep F3=5`` gives a site whose crowd thirds are not floors."""

from __future__ import annotations

import argparse
import gzip
import json
import shutil
from pathlib import Path


def _pairs(text: str, what: str) -> dict[str, str]:
    out = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        if "=" not in item:
            raise SystemExit(f"{what}: {item!r} is not NAME=VALUE")
        k, v = (s.strip() for s in item.split("=", 1))
        out[k] = v
    return out


def _copy_floor(src: Path, dst: Path, old: str, new: str, keep: int | None) -> int:
    (dst / "path_data_files").mkdir(parents=True)
    shutil.copy(src / "floor_info.json", dst / "floor_info.json")
    plan = json.loads((src / "geojson_map.json").read_text(encoding="utf-8"))
    for f in plan.get("features") or []:
        props = f.get("properties") or {}
        if props.get("category") == "floor" and props.get("name") in (old, None):
            props["name"] = new
    (dst / "geojson_map.json").write_text(json.dumps(plan, ensure_ascii=False), encoding="utf-8")
    traces = sorted(p for p in (src / "path_data_files").iterdir() if p.name.endswith((".txt", ".txt.gz")))
    for p in traces[:keep] if keep is not None else traces:
        raw = gzip.decompress(p.read_bytes()) if p.name.endswith(".gz") else p.read_bytes()
        raw = raw.replace(f"FloorName:{old}".encode(), f"FloorName:{new}".encode(), 1)
        (dst / "path_data_files" / p.name).write_bytes(gzip.compress(raw, mtime=0) if p.name.endswith(".gz") else raw)
    return min(len(traces), keep) if keep is not None else len(traces)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("site_dir", type=Path)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--rename", default="", help="OLD=NEW,... floor names")
    ap.add_argument("--keep", default="", help="FLOOR=N,...: the first N traces of a floor (its new name)")
    ap.add_argument("--plan-only", default="", help="NAME,...: extra floors with a plan and no traces")
    a = ap.parse_args()
    rename = _pairs(a.rename, "--rename")
    keep = {k: int(v) for k, v in _pairs(a.keep, "--keep").items()}
    floors = sorted(d for d in a.site_dir.iterdir() if (d / "geojson_map.json").is_file())
    if not floors:
        raise SystemExit(f"{a.site_dir}: no floor folders (with geojson_map.json)")
    if unknown := set(rename) - {d.name for d in floors}:
        raise SystemExit(f"--rename: no floor {sorted(unknown)} in {a.site_dir}")
    if a.out_dir.exists() and any(a.out_dir.iterdir()):
        raise SystemExit(f"{a.out_dir} exists and is not empty")
    a.out_dir.mkdir(parents=True, exist_ok=True)
    written = {}
    for d in floors:
        new = rename.get(d.name, d.name)
        written[new] = _copy_floor(d, a.out_dir / new, d.name, new, keep.get(new))
        print(f"{d.name} -> {new}: {written[new]} traces")
    for i, name in enumerate(filter(None, (t.strip() for t in a.plan_only.split(",")))):
        dst = a.out_dir / name
        _copy_floor(floors[-1], dst, floors[-1].name, name, 0)
        if i > 0:
            (dst / "path_data_files").rmdir()
        written[name] = 0
        print(f"{name}: a plan, no traces")
    print(json.dumps({"floors": written, "traces": sum(written.values())}))


if __name__ == "__main__":
    main()
