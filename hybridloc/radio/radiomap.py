"""Radio maps: what each transmitter looks like at each place of each floor of a site.

Model
-----
Per floor, a grid of square cells (``cell`` m, default 1.5) clipped to the walkable area of the floor
plan (or to the surveyed area plus a margin when there is no plan). For every cell c and transmitter
j the map holds the RSSI mean mu[c, j] (dBm), its standard deviation sd[c, j] (dB) and the detection
probability pd[c, j], plus the raw sample count per cell.

Interpolation to unvisited cells: Gaussian-kernel regression of the per-cell statistics (kernel
sigma ``bandwidth`` m, truncated at 3 sigma) with a prior of weight ``prior_weight`` samples pulling
towards the transmitter's floor-wide mean. This is the posterior mean of a Gaussian process with a
squared-exponential kernel under the usual Nadaraya-Watson approximation (each cell's neighbourhood
treated as exchangeable), at a cost proportional to the data instead of cubic in it: a GP per
transmitter is ~10^3 GPs of ~10^3-10^4 points per floor, which the 30 s build budget for 100,000 scans
cannot afford. The uncertainty grows as the effective detection count n_d falls away from the data:
sd^2 = shadow_sd^2 + s_floor^2 * prior_weight / (n_d + prior_weight), s_floor the floor-wide spread.
With ``prior="path-loss"`` the prior is a log-distance model fitted to each transmitter's readings
(:mod:`.pathloss`: its predicted mean, its detection law, its fit's residual spread in place of
s_floor), and ``reach_m`` may keep cells beyond the kernel's reach, where the model alone speaks. On ILC
site1 (``eval fingerprint``) the cell likelihood comes 27 % closer with it (6.94 -> 5.04 m per scan;
the weighted kNN, the server's locator, 4.76 m); on routes held out whole it ties the kNN (6.89 against
6.93 m), and carried 30 m past the labels it places the scans beyond 10 m from every label at 17.2 m
(the kNN 19.2 m) but those 5-10 m away worse (14.4 against 12.4 m): 7.00 m over all. Not the default.

Time: every sample is weighted by 0.5^(age / half_life) (age relative to the newest scan), so
transmitters that move or vanish fade out and new ones appear as soon as they are seen; each
transmitter keeps its last-seen time.

Devices: RSSI offsets per device model are estimated after a first pass (median residual against the
map) and removed before the final pass; the offsets are kept in the map for positioning.

File format (one portable ``.npz`` file, see docs/radiomap.md): a JSON header under key ``meta``
(format name, version, site, floors, grids, transmitter ids, device offsets, build parameters) and
one array set per floor: ``<floor>/cells`` (n, 2) cell centres, ``<floor>/mu``, ``<floor>/sd``,
``<floor>/pd`` (n, m) float32, ``<floor>/count`` (n,), ``<floor>/support`` (n,) n_eff.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
from scipy import sparse
from scipy.spatial import cKDTree

from ..types import FloorPlan
from .survey import LabelledScan

FORMAT_NAME = "hybridloc-radiomap"
FORMAT_VERSION = 1
#: What a map says where its data are thin (BuildParams.prior); the first is the default
PRIORS = ("floor-mean", "path-loss")
#: RSSI assumed for a transmitter at the edge of detection, dBm (prior mean for barely-seen cells).
FLOOR_DBM = -100.0


@dataclass
class BuildParams:
    cell: float = 1.5  # m
    bandwidth: float = 2.0  # m, Gaussian kernel sigma
    prior_weight: float = 0.5  # samples
    shadow_sd: float = 5.0  # dB, spread of single readings around the local mean
    margin: float = 6.0  # m around the data when there is no floor plan
    min_samples: int = 3  # detections for a transmitter to enter the map
    half_life_days: float = 90.0
    estimate_device_offsets: bool = True
    max_age_s: float | None = None  # readings older than this at scan time are left out (stale cache)
    #: weigh each labelled scan by how well its position is known: w = 1 / (1 + (sigma_label / bandwidth)^2),
    #: the share of a Gaussian label of sd sigma_label that falls within the kernel (crowd maps, whose labels
    #: range from survey-grade to metres; surveys keep equal weights)
    label_weight: bool = False
    #: what the map says where its data are thin: "floor-mean" (each transmitter's floor-wide mean RSSI,
    #: detection 2 %) or "path-loss" (a log-distance model fitted per transmitter, pathloss.py)
    prior: str = PRIORS[0]
    #: cells are kept within this distance of a labelled scan, m (default: 3 bandwidths and a cell, where
    #: the kernel reaches; with the path-loss prior a cell farther out holds the model's prediction)
    reach_m: float | None = None


@dataclass
class FloorMap:
    name: str
    cells: np.ndarray  # (n, 2) cell centres, m
    mu: np.ndarray  # (n, m) dBm
    sd: np.ndarray  # (n, m) dB
    pd: np.ndarray  # (n, m) detection probability
    count: np.ndarray  # (n,) raw labelled scans per cell
    support: np.ndarray  # (n,) effective (kernel-weighted) scans
    cell_size: float
    tx: np.ndarray  # (m_f,) indices into RadioMap.transmitters of this floor's columns
    _tree: cKDTree | None = field(default=None, repr=False)

    @property
    def tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.cells)
        return self._tree

    def cell_polygon(self, i: int):
        x, y = self.cells[i]
        h = self.cell_size / 2
        return shapely.box(x - h, y - h, x + h, y + h)


@dataclass
class RadioMap:
    site: str
    technology: str
    transmitters: list[str]
    floors: dict[str, FloorMap]
    device_offsets: dict[str, float]
    last_seen: np.ndarray  # (m,) newest time each transmitter was seen, s
    built_at: float  # newest scan time used, s
    params: BuildParams
    floor_levels: dict[str, int] = field(default_factory=dict)
    #: The labelled scans the map was built from (kept for kNN positioning and for rebuilding).
    references: list[LabelledScan] = field(default_factory=list)

    @property
    def tx_index(self) -> dict[str, int]:
        if not hasattr(self, "_tx_index"):
            self._tx_index = {t: i for i, t in enumerate(self.transmitters)}
        return self._tx_index

    # ------------------------------------------------------------------ file format
    def save(self, path: str | os.PathLike) -> None:
        meta = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "site": self.site,
            "technology": self.technology,
            "transmitters": self.transmitters,
            "floors": [{"name": f.name, "cell_size": f.cell_size, "level": self.floor_levels.get(f.name)} for f in self.floors.values()],
            "device_offsets": self.device_offsets,
            "built_at": self.built_at,
            "params": _params_header(self.params),
        }
        arrays = {"meta": np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8), "last_seen": self.last_seen}
        arrays.update(_references_to_arrays(self.references, self.tx_index))
        for f in self.floors.values():
            k = f"floor{list(self.floors).index(f.name)}"
            arrays[f"{k}/cells"] = f.cells.astype(np.float64)
            arrays[f"{k}/mu"] = f.mu.astype(np.float32)
            arrays[f"{k}/sd"] = f.sd.astype(np.float32)
            arrays[f"{k}/pd"] = f.pd.astype(np.float32)
            arrays[f"{k}/count"] = f.count.astype(np.int32)
            arrays[f"{k}/support"] = f.support.astype(np.float32)
            arrays[f"{k}/tx"] = f.tx.astype(np.int32)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)  # as the commands' --out folders are made
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, **arrays)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> RadioMap:
        if isinstance(path, (str, os.PathLike)) and not Path(path).is_file():
            from ..errors import MissingData

            raise MissingData(f"{path}: is a folder, expected a radio map file" if Path(path).is_dir() else f"{path}: no such radio map file")
        try:
            z = np.load(path, allow_pickle=False)
            meta = json.loads(bytes(z["meta"]).decode("utf-8"))
        except (OSError, ValueError, KeyError) as exc:
            # numpy reads anything that is not .npy/.npz as a pickle, and refuses it with a word about trust
            why = "not a .npz file" if "pickled" in str(exc) else str(exc)
            raise ValueError(f"{path}: not a hybridloc radio map ({why})") from exc
        if meta.get("format") != FORMAT_NAME:
            raise ValueError(f"{path}: not a hybridloc radio map (format {meta.get('format')!r})")
        if int(meta.get("version", 0)) > FORMAT_VERSION:
            raise ValueError(f"{path}: radio map version {meta['version']} is newer than this hybridloc understands ({FORMAT_VERSION})")
        floors = {}
        levels = {}
        for i, fm in enumerate(meta["floors"]):
            k = f"floor{i}"
            floors[fm["name"]] = FloorMap(
                fm["name"],
                z[f"{k}/cells"],
                z[f"{k}/mu"],
                z[f"{k}/sd"],
                z[f"{k}/pd"],
                z[f"{k}/count"],
                z[f"{k}/support"],
                float(fm["cell_size"]),
                z[f"{k}/tx"],
            )
            if fm.get("level") is not None:
                levels[fm["name"]] = int(fm["level"])
        txs = list(meta["transmitters"])
        return cls(
            meta["site"],
            meta["technology"],
            txs,
            floors,
            {k: float(v) for k, v in meta["device_offsets"].items()},
            z["last_seen"],
            float(meta["built_at"]),
            _params_from_header(meta["params"]),
            levels,
            _references_from_arrays(z, txs, meta["technology"]),
        )


#: Build parameters added after version 1's first files: written only when they differ from their
#: default, so a map built with the defaults is the very file older hybridloc wrote and reads
_LATER_PARAMS = {"prior": PRIORS[0], "reach_m": None}


def _params_header(p: BuildParams) -> dict:
    return {k: v for k, v in p.__dict__.items() if not (k in _LATER_PARAMS and v == _LATER_PARAMS[k])}


def _params_from_header(d: dict) -> BuildParams:
    """The build parameters of a file: the ones this version knows (a later version's extra settings only
    describe how its map was built; the arrays are what positioning reads)."""
    known = {f.name for f in dataclasses.fields(BuildParams)}
    return BuildParams(**{k: v for k, v in d.items() if k in known})


def _references_to_arrays(refs: list[LabelledScan], tix: dict[str, int]) -> dict[str, np.ndarray]:
    """Reference scans as flat arrays: one row per reading (ref index, transmitter index, dBm, age)."""
    fl_names = sorted({r.floor or "" for r in refs})
    fl_idx = {f: i for i, f in enumerate(fl_names)}
    ri, tj, val, age = [], [], [], []
    extra: dict[str, int] = {}
    for i, r in enumerate(refs):
        for k, v in r.scan.rssi_dbm.items():
            j = tix.get(k)
            if j is None:  # a transmitter too rare for the map: keep it for kNN under an extra index
                j = extra.setdefault(k, len(tix) + len(extra))
            ri.append(i)
            tj.append(j)
            val.append(v)
            age.append(r.scan.age_s.get(k, 0.0))
    return {
        "ref/t": np.array([r.scan.t for r in refs], float),
        "ref/pos": np.array([r.pos_enu for r in refs], float).reshape(-1, 2),
        "ref/sigma": np.array([r.sigma for r in refs], float),
        "ref/floor": np.array([fl_idx[r.floor or ""] for r in refs], np.int32),
        "ref/floor_names": np.frombuffer(json.dumps(fl_names).encode(), np.uint8),
        "ref/extra_tx": np.frombuffer(json.dumps(list(extra)).encode(), np.uint8),
        "ref/device": np.frombuffer(json.dumps([r.scan.device_model for r in refs]).encode(), np.uint8),
        # who labelled each reference (a survey device, or a crowd walk's id): a SLAM batch must not fix a
        # walk to its own labels (slam.online.CrowdSlam.set_map), also when the map comes from a file
        "ref/source": np.frombuffer(json.dumps([r.source for r in refs]).encode(), np.uint8),
        "ref/i": np.array(ri, np.int32),
        "ref/j": np.array(tj, np.int32),
        "ref/rssi": np.array(val, np.float32),
        "ref/age": np.array(age, np.float32),
    }


def _references_from_arrays(z, txs: list[str], technology: str) -> list[LabelledScan]:
    from ..types import RfScan

    if "ref/t" not in z:
        return []
    names = txs + json.loads(bytes(z["ref/extra_tx"]).decode())
    fl_names = json.loads(bytes(z["ref/floor_names"]).decode())
    devices = json.loads(bytes(z["ref/device"]).decode())
    t, pos, sig, fl = z["ref/t"], z["ref/pos"], z["ref/sigma"], z["ref/floor"]
    sources = json.loads(bytes(z["ref/source"]).decode()) if "ref/source" in z else [""] * len(t)  # older files: unknown
    ri, tj, val, age = z["ref/i"], z["ref/j"], z["ref/rssi"], z["ref/age"]
    order = np.argsort(ri, kind="stable")
    bounds = np.searchsorted(ri[order], np.arange(len(t) + 1))
    out = []
    for i in range(len(t)):
        sel = order[bounds[i] : bounds[i + 1]]
        rssi = {names[j]: float(v) for j, v in zip(tj[sel], val[sel])}
        ages = {names[j]: float(a) for j, a in zip(tj[sel], age[sel])}
        out.append(
            LabelledScan(
                RfScan(float(t[i]), technology, rssi, age_s=ages, device_model=devices[i]), pos[i], float(sig[i]), fl_names[fl[i]] or None, sources[i]
            )
        )
    return out


# ---------------------------------------------------------------------- building
def _grid_cells(points: np.ndarray, cell: float, margin: float, walkable=None) -> np.ndarray:
    if walkable is not None:
        x0, y0, x1, y1 = walkable.bounds
    else:
        x0, y0 = points.min(0) - margin
        x1, y1 = points.max(0) + margin
    xs = np.arange(x0 + cell / 2, x1, cell)
    ys = np.arange(y0 + cell / 2, y1, cell)
    gx, gy = np.meshgrid(xs, ys)
    c = np.column_stack([gx.ravel(), gy.ravel()])
    if walkable is not None:
        c = c[shapely.contains_xy(walkable, c[:, 0], c[:, 1])]
    else:
        d, _ = cKDTree(points).query(c, k=1)
        c = c[d <= margin]
    return c


@dataclass
class _Readings:
    """All readings of a set of scans as flat arrays (one Python pass; everything after is numpy)."""

    scan: np.ndarray  # (R,) scan index
    tx: np.ndarray  # (R,) global transmitter index
    rssi: np.ndarray  # (R,) dBm
    t: np.ndarray  # (S,) scan times
    pos: np.ndarray  # (S, 2)
    sigma: np.ndarray  # (S,) label sd, m
    floor: np.ndarray  # (S,) floor index
    device: np.ndarray  # (S,) device index
    floors: list[str]
    devices: list[str]
    txs: list[str]


def _collect(scans: list[LabelledScan], max_age_s: float | None) -> _Readings:
    tix: dict[str, int] = {}
    fl: dict[str, int] = {}
    dv: dict[str, int] = {}
    si, tj, rv = [], [], []
    for i, ls in enumerate(scans):
        ages = ls.scan.age_s if max_age_s is not None else None
        for k, r in ls.scan.rssi_dbm.items():
            if ages is not None and ages.get(k, 0.0) > max_age_s:
                continue
            j = tix.get(k)
            if j is None:
                j = tix[k] = len(tix)
            si.append(i)
            tj.append(j)
            rv.append(r)
    return _Readings(
        np.asarray(si, np.int64),
        np.asarray(tj, np.int64),
        np.asarray(rv, np.float64),
        np.array([ls.scan.t for ls in scans]),
        np.array([ls.pos_enu for ls in scans], float).reshape(-1, 2),
        np.array([ls.sigma for ls in scans], float),
        np.array([fl.setdefault(ls.floor or "0", len(fl)) for ls in scans]),
        np.array([dv.setdefault(ls.scan.device_model, len(dv)) for ls in scans]),
        list(fl),
        list(dv),
        list(tix),
    )


def build_radio_map(
    labelled: list[LabelledScan], site: str = "", plan: FloorPlan | None = None, params: BuildParams | None = None, technology: str = "wifi"
) -> RadioMap:
    """Build a radio map from labelled scans of one technology (see the module docstring)."""
    p = params or BuildParams()
    if p.prior not in PRIORS:
        raise ValueError(f"BuildParams.prior must be one of {PRIORS}, not {p.prior!r}")
    if p.reach_m is not None and not p.reach_m > 0:
        raise ValueError(f"BuildParams.reach_m must be a positive distance in metres, not {p.reach_m!r}")
    scans = [ls for ls in labelled if ls.scan.technology.value == technology]
    if not scans:
        raise ValueError(f"no labelled {technology} scans to build a map from")
    rd = _collect(scans, p.max_age_s)
    if rd.rssi.size == 0:
        raise ValueError("the labelled scans hold no readings")
    t_new = float(rd.t.max())
    n_tx_all = len(rd.txs)
    counts = np.bincount(rd.tx, minlength=n_tx_all)
    last = np.full(n_tx_all, -np.inf)
    np.maximum.at(last, rd.tx, rd.t[rd.scan])
    keep_tx = np.flatnonzero(counts >= p.min_samples)
    if keep_tx.size == 0:
        raise ValueError("no transmitter was detected often enough to map")
    # global map index of every kept transmitter, sorted by name for a stable file
    order = sorted(keep_tx.tolist(), key=lambda j: rd.txs[j])
    txs = [rd.txs[j] for j in order]
    gmap = np.full(n_tx_all, -1, np.int64)
    gmap[order] = np.arange(len(order))
    keep = gmap[rd.tx] >= 0
    R = _Readings(rd.scan[keep], gmap[rd.tx[keep]], rd.rssi[keep], rd.t, rd.pos, rd.sigma, rd.floor, rd.device, rd.floors, rd.devices, txs)
    dev_off = np.zeros(len(R.devices))
    floors: dict[str, FloorMap] = {}
    for _pass in range(2 if (p.estimate_device_offsets and len(R.devices) > 1) else 1):
        floors = {}
        for fi, fname in enumerate(R.floors):
            walk = None
            if plan is not None:
                try:
                    walk = plan.floor(fname).walkable
                except KeyError:
                    walk = None
            floors[fname] = _build_floor(fname, fi, R, dev_off, p, t_new, walk)
        if _pass == 0 and len(R.devices) > 1:
            dev_off = _device_offsets(floors, R)
    offsets = {d: float(dev_off[i]) for i, d in enumerate(R.devices)}
    levels = {f.name: f.level for f in plan.floors} if plan is not None else {}
    return RadioMap(site, technology, txs, floors, offsets, last[order], t_new, p, levels, list(scans))


def _build_floor(name: str, fi: int, R: _Readings, dev_off: np.ndarray, p: BuildParams, t_new: float, walkable) -> FloorMap:
    sel_scans = np.flatnonzero(R.floor == fi)
    pts = R.pos[sel_scans]
    # without a plan the grid spans the data plus the margin: a reach beyond it widens the grid
    cells = _grid_cells(pts, p.cell, p.margin if p.reach_m is None else max(p.margin, p.reach_m), walkable)
    if len(cells):
        # Keep the cells the data informs: within 3 kernel sigmas (plus a cell) of a labelled scan.
        d, _ = cKDTree(pts).query(cells, k=1)
        cells = cells[d <= (3 * p.bandwidth + p.cell if p.reach_m is None else p.reach_m)]
    if len(cells) == 0:
        raise ValueError(f"floor {name}: no walkable cell near the data")
    tree = cKDTree(cells)
    _, ci_local = tree.query(pts, k=1)
    n_cells = len(cells)
    local = np.full(len(R.t), -1, np.int64)
    local[sel_scans] = np.arange(len(sel_scans))
    rsel = local[R.scan] >= 0
    r_scan = local[R.scan[rsel]]
    r_tx = R.tx[rsel]
    r_val = R.rssi[rsel] - dev_off[R.device[sel_scans][r_scan]]
    # this floor's transmitters: detected here at least min_samples times
    cnt_tx = np.bincount(r_tx, minlength=len(R.txs))
    ftx = np.flatnonzero(cnt_tx >= p.min_samples)
    col = np.full(len(R.txs), -1, np.int64)
    col[ftx] = np.arange(len(ftx))
    k = col[r_tx] >= 0
    r_scan, r_col, r_val = r_scan[k], col[r_tx[k]], r_val[k]
    m = len(ftx)
    S = len(sel_scans)
    age_days = (t_new - R.t[sel_scans]) / 86400.0
    w = 0.5 ** (np.maximum(age_days, 0.0) / p.half_life_days)
    if p.label_weight:
        w = w / (1.0 + (R.sigma[sel_scans] / p.bandwidth) ** 2)
    det = sparse.csr_matrix((np.ones(len(r_scan)), (r_scan, r_col)), shape=(S, m))
    rs = sparse.csr_matrix((r_val, (r_scan, r_col)), shape=(S, m))
    rs2 = sparse.csr_matrix((r_val**2, (r_scan, r_col)), shape=(S, m))
    A = sparse.csr_matrix((w, (ci_local, np.arange(S))), shape=(n_cells, S))
    n_c = np.asarray(A.sum(axis=1)).ravel()
    D_c, R_c, R2_c = A @ det, A @ rs, A @ rs2
    # Gaussian kernel between cells, truncated at 3 sigma, diagonal 1
    K = tree.sparse_distance_matrix(tree, 3 * p.bandwidth, output_type="coo_matrix")
    Kw = sparse.csr_matrix((np.exp(-0.5 * (K.data / p.bandwidth) ** 2), (K.row, K.col)), shape=(n_cells, n_cells))
    Kw = Kw + sparse.identity(n_cells, format="csr") - sparse.diags(Kw.diagonal())
    n_eff = Kw @ n_c
    D_s = (Kw @ D_c).toarray().astype(np.float32)
    R_s = (Kw @ R_c).toarray().astype(np.float32)
    tot_det = np.asarray(D_c.sum(axis=0)).ravel()
    mu0 = np.where(tot_det > 0, np.asarray(R_c.sum(axis=0)).ravel() / np.maximum(tot_det, 1e-12), FLOOR_DBM)
    var0 = np.where(tot_det > 1, np.asarray(R2_c.sum(axis=0)).ravel() / np.maximum(tot_det, 1e-12) - mu0**2, 100.0)
    var0 = np.clip(var0, 9.0, 400.0).astype(np.float32)
    a = np.float32(p.prior_weight)
    # Far from detections the prior says: rarely seen (p_d 0.02); the RSSI prior is the transmitter's
    # floor-wide mean. Near data both are the kernel-weighted local estimates.
    pd_prior: np.ndarray = np.float32(0.02)
    mu_prior = mu0.astype(np.float32)[None, :]
    var_prior = var0[None, :]
    if p.prior == "path-loss":
        # the prior from a path-loss model of each transmitter fitted here (pathloss.py), where it fitted
        from .pathloss import fit_path_loss

        pl = fit_path_loss(pts, r_scan, r_col, r_val, m, weights=w)
        mu_pl = pl.mean(cells)
        mu_prior = np.where(pl.ok[None, :], mu_pl, mu_prior)
        pd_prior = np.where(pl.ok[None, :], pl.detection(mu_pl), np.float32(0.02))
        var_prior = np.where(pl.ok, pl.resid_sd**2, var0).astype(np.float32)[None, :]
    pd = (D_s + a * pd_prior) / (n_eff[:, None].astype(np.float32) + a)
    mu = (R_s + a * mu_prior) / (D_s + a)
    # Spread: temporal/shadowing noise of a reading (``shadow_sd``) plus the uncertainty of the local
    # mean, which falls back to the prior's spread (the floor-wide one, or the model fit's) where the
    # data are thin.
    var = np.float32(p.shadow_sd**2) + var_prior * a / (D_s + a)
    pd = np.clip(pd, 0.005, 0.995)
    cnt = np.bincount(ci_local, minlength=n_cells)
    return FloorMap(
        name, cells, mu.astype(np.float32), np.sqrt(var).astype(np.float32), pd.astype(np.float32), cnt, n_eff.astype(np.float32), p.cell, ftx
    )


def _device_offsets(floors: dict[str, FloorMap], R: _Readings) -> np.ndarray:
    """Median residual (reading - map mean at the labelled cell, where p_d > 0.5) per device model,
    relative to the median device, dB."""
    res_dev, res_val = [], []
    for fi, fname in enumerate(R.floors):
        fm = floors[fname]
        sel = np.flatnonzero(R.floor == fi)
        _, ci = fm.tree.query(R.pos[sel], k=1)
        cell_of = np.full(len(R.t), -1, np.int64)
        cell_of[sel] = ci
        col = np.full(len(R.txs), -1, np.int64)
        col[fm.tx] = np.arange(len(fm.tx))
        c = cell_of[R.scan]
        j = col[R.tx]
        ok = (c >= 0) & (j >= 0)
        c, j, sc = c[ok], j[ok], R.scan[ok]
        strong = fm.pd[c, j] > 0.5
        res_val.append(R.rssi[ok][strong] - fm.mu[c[strong], j[strong]])
        res_dev.append(R.device[sc[strong]])
    dev = np.concatenate(res_dev) if res_dev else np.zeros(0, int)
    val = np.concatenate(res_val) if res_val else np.zeros(0)
    med = np.array([np.median(val[dev == d]) if np.any(dev == d) else np.nan for d in range(len(R.devices))])
    ref = np.nanmedian(med) if np.isfinite(med).any() else 0.0
    return np.nan_to_num(med - ref)
