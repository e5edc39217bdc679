"""A load test for ``hybridloc eval crowd`` at about twice a site's walks (issue #21: a site of about 500
walks in under 20 minutes; only site1, 305 walks, is shared). Writes an Indoor Location Competition site
folder holding every walk of SITE_DIR and a copy of it recorded DAYS later (every timestamp shifted:
the rows' first column, the header's startTime/endTime, the WiFi and beacon rows' last-seen times)
under another id (the id's first hex digit turned to ``f``). The floor plans are copied as they are.

The copies repeat their originals' routes and scans exactly, so loop detection finds them easily and
the accuracy figures of a run mean nothing: only its time does (the server stores, adds and re-solves
twice the walks, and every batch solves floors of twice the size).

``--copies N`` copies only N walks (every walk when left out), spaced evenly along all the walks in
floor-then-file-name order, so each floor gets its share give or take one walk; site1 (305 walks)
with ``--copies 195`` makes a site of 500 walks.

Usage: python scripts/double_site.py SITE_DIR OUT_DIR [--days 7] [--copies N]
then:  hybridloc eval crowd OUT_DIR --survey-fraction 0.1 --out RUN_DIR"""

import argparse
import gzip
import shutil
import sys
from pathlib import Path

import numpy as np

#: rows whose last field is a last-seen time (ms, the recording clock)
TIMED_ROWS = ("TYPE_WIFI", "TYPE_BEACON")


def _open(path: Path):
    return gzip.open(path, "rt", encoding="utf-8") if path.suffix == ".gz" else open(path, encoding="utf-8")


def shifted(lines: list[str], shift_ms: int) -> list[str]:
    out = []
    for ln in lines:
        if ln.startswith("#"):
            for key in ("startTime:", "endTime:"):
                if key in ln:
                    head, tail = ln.split(key, 1)
                    num = tail[: next((i for i, ch in enumerate(tail) if not ch.isdigit()), len(tail))]
                    if num:
                        ln = head + key + str(int(num) + shift_ms) + tail[len(num) :]
            out.append(ln)
        elif ln.strip():
            t, _, rest = ln.partition("\t")
            if not t.strip().isdigit() or not rest:
                out.append(ln)  # a line the reader skips and counts: copied as it is
                continue
            parts = rest.split("\t")
            if parts[0] in TIMED_ROWS and parts[-1].strip().isdigit():
                parts[-1] = str(int(parts[-1]) + shift_ms)
            out.append(str(int(t) + shift_ms) + "\t" + "\t".join(parts))
        else:
            out.append(ln)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("site", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--days", type=float, default=7.0, help="how much later the copies were recorded")
    ap.add_argument("--copies", type=int, default=None, help="how many walks get a copy (default: all)")
    args = ap.parse_args(argv)
    shift_ms = int(round(args.days * 86400 * 1000))
    floors = sorted(p for p in args.site.iterdir() if p.is_dir() and (p / "path_data_files").is_dir())
    if not floors:
        print(f"{args.site}: no floor folders with path_data_files", file=sys.stderr)
        return 2
    files = {fl: sorted((fl / "path_data_files").iterdir()) for fl in floors}
    n_all = sum(len(v) for v in files.values())
    n_copy = n_all if args.copies is None else args.copies
    if not 0 <= n_copy <= n_all:
        print(f"--copies must be in [0, {n_all}]", file=sys.stderr)
        return 2
    # which walks get a copy: evenly spaced over all walks in (floor, file name) order
    order = [(fl, f) for fl in floors for f in files[fl]]
    pick = {order[i] for i in np.unique(np.floor(np.arange(n_copy) * n_all / n_copy).astype(int))} if n_copy else set()
    n = 0
    for fl in floors:
        dst = args.out / fl.name
        (dst / "path_data_files").mkdir(parents=True, exist_ok=True)
        for f in fl.iterdir():
            if f.is_file():
                shutil.copy(f, dst / f.name)
        for f in files[fl]:
            shutil.copy(f, dst / "path_data_files" / f.name)
            if (fl, f) not in pick:
                continue
            wid, rest = f.name.split(".", 1)
            twin = dst / "path_data_files" / (("f" if wid[0] != "f" else "e") + wid[1:] + "." + rest)
            with _open(f) as src:
                lines = src.read().split("\n")
            opener = gzip.open if twin.suffix == ".gz" else open
            with opener(twin, "wt", encoding="utf-8") as out:
                out.write("\n".join(shifted(lines, shift_ms)))
            n += 1
    print(f"{args.out}: {n_all + n} walks ({n_all} and copies of {n} of them {args.days:g} days later) on {len(floors)} floors")
    return 0


if __name__ == "__main__":
    sys.exit(main())
