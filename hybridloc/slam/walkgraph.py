"""A walk as part of the crowd graph: its nodes, their dead-reckoned positions and odometry.

Nodes (slam.md 4.2): one per WiFi scan (at the scan's time; other technologies are labelled from the
corrected track), one at each sharp turn (the heading
changes by more than ``turn_deg`` within ``turn_window`` steps), one at each survey mark, and one at
the walk's start and end. A walk that changes floor is cut into pieces, one per floor (the stairs
between them carry no node: their horizontal motion is not what the floor graph models).

Odometry between consecutive nodes i -> j of a piece is the dead-reckoned displacement

    D_ij = q(t_j) - q(t_i),   q(t) = sum over steps k with t_k <= t of l_k u(psi_k)         (slam.md 4.2)

(linearly interpolated inside a step, as :class:`~hybridloc.pdr.deadreckoning.DeadReckoning` does),
with the covariance of its WHITE error only:

    S_ij = sum_k ( sigma_l,k^2 u u^T + l_k^2 sigma_w,k^2 u_perp u_perp^T + sigma_0^2 I )

sigma_w,k is the step's heading-change sigma (the gyro's white noise) where the PDR gives it, else its
absolute heading sigma; sigma_0 (``sigma_model_m``) covers the step model's own error. The correlated
errors, step-length scale and heading bias, are explicit unknowns per ``segment_s`` segment of the
walk (:mod:`hybridloc.slam.factors`: r = p_j - p_i - (a D + b D_perp)), so they are not folded into S.
Cumulative covariance C(t) (the sum above from the walk's start) gives Cov(q_j - q_i) = C_j - C_i for
the front end's consistency test.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..types import RfScan, StepEvent, SurveyMark, Technology, Walk, WalkEnd

KIND_END = 0
KIND_SCAN = 1
KIND_TURN = 2
KIND_MARK = 3
KIND_BEACON = 4
#: standard deviation added to every odometry edge, m (nodes at the same time share no step)
MIN_EDGE_SD_M = 0.05


@dataclass
class WalkGraphConfig:
    #: a node where the heading turns by more than this within ``turn_window`` steps (Zee, C-SLAM-RF)
    turn_deg: float = 45.0
    turn_window: int = 3
    #: one (scale, heading-bias) unknown per this much walking time; consecutive ones random-walk
    segment_s: float = 20.0
    #: white step-model error per step, m (slam.md 4.2: sigma_0 ~ 0.1 m)
    sigma_model_m: float = 0.1
    #: heading white noise per step when the PDR gives no heading-change sigma, rad (capped absolute sigma)
    sigma_heading_white_max: float = math.radians(5.0)
    #: nuisance priors (slam.md 3.1: scale truth/PDR median 0.89, IQR 0.81-0.97 -> sd 0.1; heading vs
    #: plan frame per walk median 5.4 deg, p90 15.7 deg -> sd 8 deg) and their drift between segments
    scale_sd: float = 0.1
    bias_sd: float = math.radians(8.0)
    scale_drift_sd: float = 0.02
    bias_drift_sd: float = 0.05
    #: readings older than this at scan time are stale (slam.md 3.1: 4 s on site1)
    max_age_s: float = 4.0
    #: scans of these technologies are graph nodes (loops and fixes act on them); the others (BLE
    #: adverts, several per second) are labelled from the corrected track at their time
    node_technologies: tuple[str, ...] = ("wifi",)
    #: beacon passes: a node where a beacon of these technologies is heard strongest, if at least this loud.
    #: site1 (truth used only to check the physics): beacons heard at >= -65 dBm lie a median 2.2-3.6 m
    #: from the centre of where all walks heard them so (a -59 dBm-at-1-m iBeacon, path-loss exponent 2-3)
    beacon_technologies: tuple[str, ...] = ("ble",)
    beacon_min_dbm: float = -65.0


@dataclass
class WalkPiece:
    """One walk on one floor: the nodes it contributes to that floor's graph (module docstring)."""

    walk: int  # index of the walk in the caller's list
    name: str
    floor: str
    t: np.ndarray  # (n,) s
    kind: np.ndarray  # (n,) KIND_*
    q: np.ndarray  # (n, 2) dead-reckoned position in the walk's own frame, m
    C: np.ndarray  # (n, 2, 2) cumulative white dead-reckoning covariance, m^2
    scan: np.ndarray  # (n,) index into ``scans`` of the scan at the node, or -1
    mark: np.ndarray  # (n,) index into ``marks`` of the mark at the node, or -1
    beacon: np.ndarray  # (n,) index into ``beacons`` of the beacon heard strongest at the node, or -1
    segment: np.ndarray  # (n - 1,) nuisance segment (0, 1, ...) of each odometry edge
    scans: list[RfScan]
    marks: list[SurveyMark]
    beacons: list[str]  # ids of the beacons this piece passed (heard at >= beacon_min_dbm)
    beacon_dbm: list[float]  # the strongest reading of each
    step_t: np.ndarray  # (m,) the piece's step times, s
    step_q: np.ndarray  # (m, 2) dead-reckoned positions after each step, walk frame
    device_model: str = ""
    node0: int = -1  # first graph node id, once added to a graph
    nuisance: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # graph nuisance ids per segment

    @property
    def n(self) -> int:
        return len(self.t)

    @property
    def nodes(self) -> np.ndarray:
        return self.node0 + np.arange(self.n)

    @property
    def n_segments(self) -> int:
        return int(self.segment.max()) + 1 if len(self.segment) else 1

    def q_at(self, t) -> np.ndarray:
        """Dead-reckoned positions (len(t), 2) in the walk frame at times t: linear within a step,
        held outside the piece."""
        t = np.asarray(t, float)
        return np.column_stack([np.interp(t, self.step_t, self.step_q[:, 0]), np.interp(t, self.step_t, self.step_q[:, 1])])

    def odometry(self) -> tuple[np.ndarray, np.ndarray]:
        """(D (n-1, 2), S (n-1, 2, 2)): displacement and white covariance of each edge (module docstring)."""
        D = np.diff(self.q, axis=0)
        # two nodes at one time (a scan and a mark) differ by no step: a small floor keeps S invertible
        S = np.diff(self.C, axis=0) + MIN_EDGE_SD_M**2 * np.eye(2)[None]
        return D, S


def _interp_rows(t: np.ndarray, tk: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Row-wise ``numpy.interp`` of v (m, ...) at times t, holding outside [tk[0], tk[-1]]."""
    flat = v.reshape(len(tk), -1)
    return np.stack([np.interp(t, tk, flat[:, c]) for c in range(flat.shape[1])], axis=-1).reshape((len(t),) + v.shape[1:])


def _step_arrays(steps: list[StepEvent], cfg: WalkGraphConfig, t0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(times, positions, cumulative covariance, headings) with a start row at t0 (module docstring)."""
    n = len(steps)
    t = np.empty(n + 1)
    t[0] = t0
    L = np.array([s.length for s in steps])
    psi = np.array([s.heading for s in steps])
    sl = np.array([s.sigma_length for s in steps])
    sw = np.array(
        [s.sigma_heading_change if s.sigma_heading_change is not None else min(s.sigma_heading, cfg.sigma_heading_white_max) for s in steps]
    )
    t[1:] = [s.t for s in steps]
    u = np.stack([np.cos(psi), np.sin(psi)], axis=1)
    up = np.stack([-u[:, 1], u[:, 0]], axis=1)
    q = np.zeros((n + 1, 2))
    q[1:] = np.cumsum(L[:, None] * u, axis=0)
    dC = (
        sl[:, None, None] ** 2 * np.einsum("ki,kj->kij", u, u)
        + (L * sw)[:, None, None] ** 2 * np.einsum("ki,kj->kij", up, up)
        + cfg.sigma_model_m**2 * np.eye(2)[None]
    )
    C = np.zeros((n + 1, 2, 2))
    C[1:] = np.cumsum(dC, axis=0)
    return t, q, C, psi


def scan_node_time(scan: RfScan, max_age_s: float) -> float:
    """A scan's node time: the median last-seen time of its fresh readings (slam.md 4.1), or the scan
    time when it has no reading ages. Stale readings (older than ``max_age_s``) do not count."""
    ages = [a for a in scan.age_s.values() if math.isfinite(a) and 0.0 <= a <= max_age_s]
    return float(scan.t - np.median(ages)) if ages else float(scan.t)


def walk_pieces(walk: Walk, index: int, cfg: WalkGraphConfig | None = None, name: str | None = None) -> list[WalkPiece]:
    """The walk's pieces, one per floor it walked (module docstring). A walk with fewer than two
    steps or no floor gives none."""
    cfg = cfg or WalkGraphConfig()
    steps = sorted(walk.steps, key=lambda s: s.t)
    if len(steps) < 2 or not walk.floors:
        return []
    name = name if name is not None else (str(walk.walk_id) if walk.walk_id is not None else walk.device)
    # the floor during each step: the walk's floors in order, advancing at each floor change
    floors = list(walk.floors)
    fi = np.cumsum([1 if s.floor_change != 0 else 0 for s in steps])
    fi = np.minimum(fi, len(floors) - 1)
    pieces = []
    start = 0
    for k in range(1, len(steps) + 1):
        if k == len(steps) or fi[k] != fi[start]:
            part = steps[start:k]
            if len(part) >= 2:
                p = _piece(walk, index, name, floors[int(fi[start])], part, cfg, first=start == 0, last=k == len(steps))
                if p is not None:
                    pieces.append(p)
            start = k
    return pieces


def _piece(walk: Walk, index: int, name: str, floor: str, steps: list[StepEvent], cfg: WalkGraphConfig, first: bool, last: bool) -> WalkPiece | None:
    t_lo = min(walk.t_start, steps[0].t - 1.0) if first else steps[0].t - 0.5
    t_hi = max(walk.t_end, steps[-1].t) if last else steps[-1].t
    st, sq, sC, psi = _step_arrays(steps, cfg, t_lo)
    scans = [s for s in walk.scans if t_lo <= s.t <= t_hi + 5.0 and len(s)]
    marks = [m for m in walk.marks if t_lo <= m.t <= t_hi and (not m.floor or m.floor == floor)]
    times: list[tuple] = [(t_lo, KIND_END, -1, -1), (float(st[-1]), KIND_END, -1, -1)]
    for i, s in enumerate(scans):
        if s.technology.value in cfg.node_technologies:
            times.append((min(max(scan_node_time(s, cfg.max_age_s), t_lo), t_hi), KIND_SCAN, i, -1))
    for i, m in enumerate(marks):
        times.append((m.t, KIND_MARK, -1, i))
    # beacon passes: for each beacon heard at >= beacon_min_dbm, a node at its strongest advert (the
    # closest approach; UnLoc's organic landmarks - a strong fixed BLE beacon is heard that loud only
    # within metres of it)
    peak: dict[str, tuple[float, float]] = {}
    for s in scans:
        if s.technology.value not in cfg.beacon_technologies:
            continue
        for b, r in s.rssi_dbm.items():
            if r >= cfg.beacon_min_dbm and (b not in peak or r > peak[b][1]):
                peak[b] = (s.t, r)
    beacons = sorted(peak)
    for bi, b in enumerate(beacons):
        times.append((min(max(peak[b][0], t_lo), t_hi), KIND_BEACON, -1, -1, bi))
    # sharp turns: heading change over turn_window steps beyond turn_deg; one node per turn (its middle step)
    w = cfg.turn_window
    if len(psi) > w:
        dpsi = np.abs(np.angle(np.exp(1j * (psi[w:] - psi[:-w]))))
        turning = dpsi > math.radians(cfg.turn_deg)
        k = 0
        while k < len(turning):
            if turning[k]:
                e = k
                while e + 1 < len(turning) and turning[e + 1]:
                    e += 1
                mid = (k + e) // 2 + w // 2 + 1  # step index + 1 (row in st)
                times.append((float(st[min(mid, len(st) - 1)]), KIND_TURN, -1, -1))
                k = e + 1
            else:
                k += 1
    times.sort(key=lambda r: (r[0], r[1]))
    merged = times
    t = np.array([r[0] for r in merged])
    q = _interp_rows(t, st, sq)
    C = _interp_rows(t, st, sC)
    seg = np.minimum(((0.5 * (t[:-1] + t[1:]) - t[0]) // cfg.segment_s).astype(np.int64), 10**6)
    # renumber segments densely (a long pause leaves no empty segment)
    _, seg = np.unique(seg, return_inverse=True)
    return WalkPiece(
        walk=index,
        name=name,
        floor=floor,
        t=t,
        kind=np.array([r[1] for r in merged], dtype=np.int8),
        q=q,
        C=C,
        scan=np.array([r[2] for r in merged], dtype=np.int64),
        mark=np.array([r[3] for r in merged], dtype=np.int64),
        beacon=np.array([r[4] if len(r) > 4 else -1 for r in merged], dtype=np.int64),
        segment=seg.astype(np.int64),
        scans=scans,
        marks=marks,
        beacons=beacons,
        beacon_dbm=[peak[b][1] for b in beacons],
        step_t=st,
        step_q=sq,
        device_model=walk.device_model,
    )


# ------------------------------------------------------------------------------------------------ files
def walk_from_ilc(path: str | Path, marks: bool = True, technologies: tuple[str, ...] = ("wifi", "ble")) -> tuple[Walk, object]:
    """An Indoor Location Competition recording as a :class:`~hybridloc.types.Walk` (its phone PDR with
    absolute headings, its scans, and its waypoints as survey marks unless ``marks`` is False) and the
    trace's waypoints (the caller keeps them for scoring only; with ``marks=False`` nothing else sees them)."""
    from ..io.msft import read_ilc_trace
    from ..pdr.phone import PhonePdr
    from ..pdr.steplength import make_model

    tr = read_ilc_trace(path)
    steps = PhonePdr(tr.imu.rate_hz, make_model("height"), heading0=None).process(tr.imu) if tr.imu is not None else []
    scans = tuple(s for s in tr.scans if s.technology.value in technologies and len(s))
    floor = tr.floor or ""
    wp = tr.waypoints
    mk = (
        tuple(SurveyMark(float(wp.t[i]), float(wp.pos_enu[i][0]), float(wp.pos_enu[i][1]), wp.floor_of(i) or floor) for i in range(len(wp.t)))
        if marks
        else ()
    )
    times = [s.t for s in steps] + [s.t for s in scans] + [m.t for m in mk]
    if tr.imu is not None and len(tr.imu.t):
        times += [float(tr.imu.t[0]), float(tr.imu.t[-1])]
    t0, t1 = (min(times), max(times)) if times else (0.0, 0.0)
    walk = Walk(
        site=tr.site or "",
        device=Path(path).name.split(".")[0],
        walk_id=None,
        t_start=t0,
        t_end=t1,
        device_model=tr.device_model,
        floors=(floor,) if floor else (),
        steps=tuple(steps),
        scans=scans,
        marks=mk,
        end=WalkEnd.MARKER,
    )
    return walk, wp


__all__ = [
    "KIND_BEACON",
    "KIND_END",
    "KIND_MARK",
    "KIND_SCAN",
    "KIND_TURN",
    "Technology",
    "WalkGraphConfig",
    "WalkPiece",
    "scan_node_time",
    "walk_from_ilc",
    "walk_pieces",
    "walks_from_files",
]


def _load_one(args) -> tuple[Walk, object]:
    path, marks = args
    return walk_from_ilc(path, marks=marks)


def walks_from_files(paths: list[Path], marks: list[bool] | bool = True, workers: int = 2, progress=None) -> list[tuple[Walk, object]]:
    """:func:`walk_from_ilc` over many files (phone PDR in ``workers`` processes), in the given order.
    ``marks``: one flag per file, or one for all. ``progress(done, total)`` after each file."""
    import concurrent.futures as cf

    from ..pools import process_pool

    flags = [marks] * len(paths) if isinstance(marks, bool) else list(marks)
    jobs = list(zip([str(p) for p in paths], flags))
    if workers <= 1 or len(jobs) < 4:
        out = []
        for i, j in enumerate(jobs):
            out.append(_load_one(j))
            if progress:
                progress(i + 1, len(jobs))
        return out
    out = [None] * len(jobs)
    with process_pool(workers) as ex:
        futs = {ex.submit(_load_one, j): i for i, j in enumerate(jobs)}
        for n, f in enumerate(cf.as_completed(futs)):
            out[futs[f]] = f.result()
            if progress:
                progress(n + 1, len(jobs))
    return out  # type: ignore[return-value]
