"""What ``slam run`` writes and ``slam show`` reads: corrected tracks, the loop audit, crowd maps.

Files in the output folder:

* ``tracks.csv``: ``walk,t,x,y,floor,sigma_x,sigma_y,anchored`` - every step and node of every walk,
  corrected (m, site frame, s); ``anchored`` is how the walk is tied to the site frame: ``marks``
  (survey marks), ``map`` (radio-map fixes), ``loops`` (loops to walks that have either), ``plan``
  (its group placed on the floor plan) or ``relative`` (no
  absolute position: x, y are in the walk group's own frame and must not be used as positions);
* ``raw.csv``: the same columns for the dead-reckoned walks as recorded (each in its own frame, started
  at its first corrected position), for drawing raw against corrected;
* ``tracks.geojson``: one LineString per anchored walk piece (site frame; WGS84 when the plan has a
  geodetic origin);
* ``loops.csv``: ``walk_a,t_a,walk_b,t_b,similarity,weight,accepted`` plus ``floor,p_inlier,reason,kind`` -
  every loop candidate, with its final robust weight (the audit trail). ``kind`` ``wifi``: a fingerprint
  loop (``similarity`` in [0, 1]); ``ble``: both walks passed the same beacon (``similarity`` = the
  weaker of the two peak readings, dBm);
* ``crowdmap_<technology>.npz``: the crowd radio map of each technology (docs/radiomap.md format).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np

from .pipeline import RELATIVE, LoopRecord, SlamResult

TRACK_COLUMNS = ("walk", "t", "x", "y", "floor", "sigma_x", "sigma_y", "anchored")
LOOP_COLUMNS = ("walk_a", "t_a", "walk_b", "t_b", "similarity", "weight", "accepted", "floor", "p_inlier", "reason", "kind")


def _track_rows(res: SlamResult, raw: bool = False):
    for fname, fs in sorted(res.floors.items()):
        for k, pc in enumerate(fs.pieces):
            t = np.union1d(pc.step_t, pc.t)
            if raw:
                q = pc.q_at(t)
                start = fs.pos[pc.nodes[0]] if np.all(np.isfinite(fs.pos[pc.nodes[0]])) else np.zeros(2)
                xy = q - pc.q[0] + start
                sd = np.full((len(t), 2), np.nan)
            else:
                xy = fs.track(k, t)
                sd = fs.track_sigma(k, t)
            for i in range(len(t)):
                yield (pc.name, float(t[i]), float(xy[i, 0]), float(xy[i, 1]), fname, float(sd[i, 0]), float(sd[i, 1]), fs.status[k])


def _fmt(v) -> str:
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.3f}"
    return str(v)


def write_tracks_csv(path: str | Path, res: SlamResult, raw: bool = False) -> int:
    n = 0
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(TRACK_COLUMNS)
        for row in _track_rows(res, raw):
            w.writerow([_fmt(v) for v in row])
            n += 1
    return n


def write_loops_csv(path: str | Path, loops: list[LoopRecord]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(LOOP_COLUMNS)
        for lp in loops:
            w.writerow(
                [
                    lp.walk_a,
                    f"{lp.t_a:.3f}",
                    lp.walk_b,
                    f"{lp.t_b:.3f}",
                    f"{lp.similarity:.4f}",
                    f"{lp.weight:.4f}",
                    int(lp.accepted),
                    lp.floor,
                    _fmt(lp.p_inlier),
                    lp.reason,
                ]
            )


def write_tracks_geojson(path: str | Path, res: SlamResult, plan=None) -> None:
    from ..io.writers import write_geojson

    origin = plan.origin if plan is not None else None
    feats = []
    for fname, fs in sorted(res.floors.items()):
        for k, pc in enumerate(fs.pieces):
            if fs.status[k] == RELATIVE:
                continue
            t = np.union1d(pc.step_t, pc.t)
            xy = fs.track(k, t)
            feats.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "LineString", "coordinates": xy.tolist()},
                    "properties": {
                        "kind": "corrected_track",
                        "walk": pc.name,
                        "floor": fname,
                        "anchored": fs.status[k],
                        "t0": float(t[0]),
                        "t1": float(t[-1]),
                    },
                }
            )
    write_geojson(path, feats, origin)


def write_outputs(out: str | Path, res: SlamResult, plan=None, site: str = "") -> dict:
    """Every file of the module docstring; returns {name: path or count} for the report."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = write_tracks_csv(out / "tracks.csv", res)
    write_tracks_csv(out / "raw.csv", res, raw=True)
    write_tracks_geojson(out / "tracks.geojson", res, plan)
    write_loops_csv(out / "loops.csv", res.loops)
    maps = {}
    for tech in ("wifi", "ble"):
        try:
            rm = res.crowd_map(tech, site, plan)
        except ValueError:  # too few readings of this technology to map
            rm = None
        if rm is not None:
            p = out / f"crowdmap_{tech}.npz"
            rm.save(p)
            maps[tech] = str(p)
    (out / "summary.json").write_text(json.dumps(res.stats, indent=1, sort_keys=True), encoding="utf-8")
    return {"track_rows": rows, "loops": len(res.loops), "maps": maps}


# ------------------------------------------------------------------------------------------ reading back
def read_tracks_csv(path: str | Path) -> dict[str, dict[str, np.ndarray]]:
    """{walk: {"t", "xy", "floor", "anchored"}} from a tracks.csv (or raw.csv)."""
    out: dict[str, dict] = {}
    with open(path, encoding="utf-8") as fh:
        r = csv.DictReader(fh)
        missing = set(TRACK_COLUMNS) - set(r.fieldnames or [])
        if missing:
            raise ValueError(f"{path}: not a tracks file (missing columns {sorted(missing)})")
        for row in r:
            d = out.setdefault(
                row["walk"] + "\0" + row["floor"], {"walk": row["walk"], "t": [], "xy": [], "floor": row["floor"], "anchored": row["anchored"]}
            )
            d["t"].append(float(row["t"]))
            d["xy"].append((float(row["x"]), float(row["y"])))
    for d in out.values():
        d["t"] = np.asarray(d["t"])
        d["xy"] = np.asarray(d["xy"])
    return out


def read_loops_csv(path: str | Path) -> list[dict]:
    with open(path, encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


#: rejected candidates drawn: those that were mutual matches and fell at the model, PCM or the robust back
#: end (the others - below the similarity floor, not mutual - would cover the plan; they are counted)
DRAWN_REJECTIONS = ("model", "pcm", "pcm-small", "robust-weight")


def plot_slam(ax, plan, tracks: dict, raw: dict | None, loops: list[dict], floor: str) -> dict:
    """Raw (grey) and corrected (coloured) walks of one floor over the plan, accepted loops (green) and
    the rejected ones that reached the consistency test or the back end (red). Walks that are relative
    only have no place on the plan and are counted, not drawn."""
    from matplotlib import colormaps

    from ..radio.plot import plot_plan

    plot_plan(ax, plan, floor)
    pos_at = {}
    n_walks = n_rel = 0
    cmap = colormaps["Blues"]  # walks in blues: green and red are the loops' colours
    keys = [k for k, d in sorted(tracks.items()) if d["floor"] == floor]
    for n, key in enumerate(keys):
        d = tracks[key]
        n_walks += 1
        if d["anchored"] == RELATIVE:
            n_rel += 1
            continue
        if raw and key in raw:
            ax.plot(raw[key]["xy"][:, 0], raw[key]["xy"][:, 1], color="0.6", lw=0.5, alpha=0.6)
        ax.plot(d["xy"][:, 0], d["xy"][:, 1], lw=0.9, alpha=0.9, color=cmap(0.45 + 0.55 * n / max(len(keys) - 1, 1)))
        pos_at[d["walk"]] = d
    acc = rej = drawn = 0
    for lp in loops:
        if lp.get("floor", floor) != floor:
            continue
        ok = lp["accepted"] in ("1", "True", "true")
        acc += ok
        rej += not ok
        if not ok and lp.get("reason", "") not in DRAWN_REJECTIONS:
            continue
        a, b = pos_at.get(lp["walk_a"]), pos_at.get(lp["walk_b"])
        if a is None or b is None:
            continue
        pa = np.array([np.interp(float(lp["t_a"]), a["t"], a["xy"][:, c]) for c in (0, 1)])
        pb = np.array([np.interp(float(lp["t_b"]), b["t"], b["xy"][:, c]) for c in (0, 1)])
        drawn += not ok
        ax.plot([pa[0], pb[0]], [pa[1], pb[1]], color="tab:green" if ok else "tab:red", lw=1.0 if ok else 0.4, alpha=0.9 if ok else 0.4, zorder=3)
    ax.set_aspect("equal")
    ax.set_title(
        f"floor {floor}: {n_walks} walks ({n_rel} relative only, not drawn); loops: {acc} accepted (green), {rej} rejected "
        f"({drawn} drawn in red: fell at the model, PCM or the back end); grey: raw",
        fontsize=9,
    )
    return {"walks": n_walks, "relative": n_rel, "accepted": acc, "rejected": rej}
