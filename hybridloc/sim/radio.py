"""Radio measurements of a simulated walk: WiFi, BLE, RFID, GPS.

RSSI (dBm) of transmitter j at position p on floor f:

    P0_j - 10 n log10(max(d, 1 m)) - W * walls(j, p) - F * |f - f_j| + S_j(p) + e + o_device

* log-distance path loss (P0 -38 dBm at 1 m for 2.4 GHz, -45 dBm for 5 GHz, n = 2.8; walls add
  W = 4 dB each, counted on the floor plan; floors F = 15 dB each);
* S_j: spatially correlated shadowing, a Gaussian random field (random Fourier features) with
  sigma 6 dB and correlation length 8 m: the same place looks alike, nearby places look similar;
* e: temporal noise N(0, 3.5 dB); o_device: the phone model's offset;
* a reading exists above the detection threshold (-92 dBm WiFi, -95 dBm BLE).

The four numbers n, sigma_S, its length and sigma_e are set so that fingerprints are as alike, place
to place, as real ones (``hybridloc eval sim-realism``: the median cosine similarity of two scans by
their distance apart, against ILC site1's; rms difference over the 0-2 ... 20-40 m bins 0.11 with
n = 2.2, 4 dB, 3 m, 2 dB, 0.03 with these), all within the usual indoor ranges (n 2-3.5, shadowing
4-8 dB decorrelating over metres, temporal 2-6 dB). The simulated scans keep their true positions,
the real ones carry the survey labels' metre or two of error, which lowers the real similarity of the
nearest pairs a little.

Scan throttling: a WiFi scan every ``wifi_period`` s (3-4 s, Android's foreground rate; pass 30 for
Android 9's 4 scans per 2 minutes), a BLE report per beacon per second. RFID readers at doors detect
the walker within 1.5 m and give a fix with sigma 0.4 m (Kourogi et al.). GPS works outdoors and
within ``gps_indoor_reach`` m inside the entrance, with noise sigma = 3 m x HDOP and 5 % multipath
outliers of 10-30 m (Kourogi et al. sec. 3.1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import shapely

from ..geo import wall_crossings
from ..types import AbsoluteFix, FixSource, RfScan, Technology
from .building import STOREY, World
from .walker import Walk

WALL_DB = 4.0
FLOOR_DB = 15.0
PATH_LOSS_N = 2.8
SHADOW_SD = 6.0
SHADOW_LENGTH = 8.0
TEMPORAL_SD = 3.5


RFID_RANGE = 1.5  # m, tag-to-reader detection range (Kourogi sec. 4)
RFID_TAG_H = 0.6  # m, tag at hip height
RFID_READER_H = 2.0  # m, reader in the door frame
RFID_SIGMA = 0.4  # m, per-axis sigma Kourogi measured


@dataclass
class RadioModel:
    """Precomputed per-world radio: shadowing fields and per-floor wall-attenuation grids."""

    world: World
    w: np.ndarray  # (A + B, K, 2) random Fourier wave vectors
    b: np.ndarray  # (A + B, K)
    c: np.ndarray  # (A + B, K)
    p0: np.ndarray  # (A + B,) dBm at 1 m
    tx_pos: np.ndarray  # (A + B, 3)
    grid_x: np.ndarray
    grid_y: np.ndarray
    walls_db: np.ndarray | None  # (A + B, n_floors, ny, nx) wall attenuation from tx to grid cell on each floor (None: on demand)
    shadow_x: np.ndarray  # finer grid for the shadowing field
    shadow_y: np.ndarray
    shadow_db: np.ndarray | None  # (A + B, nsy, nsx) the shadowing field sampled on it (None: on demand)


def make_radio_model(world: World, rng: np.random.Generator, n_terms: int = 32, grid: float = 1.0) -> RadioModel:
    tx = np.vstack([world.aps, world.beacons])
    n_tx = len(tx)
    w = rng.normal(0.0, 1.0 / SHADOW_LENGTH, (n_tx, n_terms, 2))
    b = rng.uniform(0, 2 * math.pi, (n_tx, n_terms))
    c = rng.normal(0.0, SHADOW_SD * math.sqrt(2.0 / n_terms), (n_tx, n_terms))
    p0 = np.concatenate([np.where(world.ap_freq_mhz < 3000, -38.0, -45.0), np.full(len(world.beacons), -59.0 + 0.0)])
    gx = np.arange(world.x_min - 15.0, world.width + 15.0 + grid, grid)
    gy = np.arange(world.y_min - 15.0, world.depth + 15.0 + grid, grid)
    sx = np.arange(world.x_min - 15.0, world.width + 15.5, 0.5)
    sy = np.arange(world.y_min - 15.0, world.depth + 15.5, 0.5)
    if n_tx * len(sx) * len(sy) > 20_000_000:
        # a large real plan with hundreds of transmitters: precomputed grids would take minutes and
        # gigabytes; rssi() evaluates the same shadowing sum and wall crossings at the scan positions
        return RadioModel(world, w, b, c, p0, tx, gx, gy, None, sx, sy, None)
    X, Y = np.meshgrid(gx, gy)
    pts = np.column_stack([X.ravel(), Y.ravel()])
    walls_db = np.zeros((n_tx, world.n_floors, len(gy), len(gx)), np.float32)
    for j in range(n_tx):
        fj = int(tx[j, 2])
        walls = world.plan.floors[fj].walls
        nw = wall_crossings(walls, np.repeat(tx[j : j + 1, :2], len(pts), axis=0), pts)
        walls_db[j, :] = (WALL_DB * nw).reshape(len(gy), len(gx))[None]
    # the shadowing field on a 0.5 m grid (correlation length 3 m: nearest-cell lookup is smooth enough)
    SX, SY = np.meshgrid(sx, sy)
    sp = np.column_stack([SX.ravel(), SY.ravel()])
    shadow = np.stack([np.cos(sp @ w[j].T + b[j]) @ c[j] for j in range(n_tx)]).reshape(n_tx, len(sy), len(sx)).astype(np.float32)
    return RadioModel(world, w, b, c, p0, tx, gx, gy, walls_db, sx, sy, shadow)


def rssi(model: RadioModel, tx_idx: np.ndarray, xy: np.ndarray, floor, rng: np.random.Generator, offset: float = 0.0) -> np.ndarray:
    """Readings of transmitters ``tx_idx`` at positions ``xy`` (S, 2) on floors (S,), dBm, shape (S, T);
    one position (2,) with an int floor gives shape (T,). No detection threshold applied."""
    single = np.ndim(xy) == 1
    xy = np.atleast_2d(np.asarray(xy, float))
    fl = np.broadcast_to(np.asarray(floor, int), (len(xy),))
    tx = model.tx_pos[tx_idx]
    dz = (fl[:, None] - tx[None, :, 2]) * STOREY
    d = np.sqrt(np.sum((tx[None, :, :2] - xy[:, None, :]) ** 2, axis=2) + dz**2)
    if model.shadow_db is not None:
        jx = np.clip(np.rint((xy[:, 0] - model.shadow_x[0]) / 0.5).astype(int), 0, len(model.shadow_x) - 1)
        jy = np.clip(np.rint((xy[:, 1] - model.shadow_y[0]) / 0.5).astype(int), 0, len(model.shadow_y) - 1)
        shadow = model.shadow_db[tx_idx][:, jy, jx].T  # (S, T)
        ix = np.clip(np.searchsorted(model.grid_x, xy[:, 0]), 0, len(model.grid_x) - 1)
        iy = np.clip(np.searchsorted(model.grid_y, xy[:, 1]), 0, len(model.grid_y) - 1)
        flc = np.minimum(fl, model.walls_db.shape[1] - 1)
        walls = model.walls_db[tx_idx][:, flc, iy, ix].T  # (S, T)
    else:  # the same sum of random Fourier features and wall crossings, at the positions themselves
        shadow = np.zeros((len(xy), len(tx_idx)))
        walls = np.zeros((len(xy), len(tx_idx)))
        for k, j in enumerate(np.atleast_1d(tx_idx)):
            shadow[:, k] = np.cos(xy @ model.w[j].T + model.b[j]) @ model.c[j]
            fw = model.world.plan.floors[int(model.tx_pos[j, 2])].walls
            walls[:, k] = WALL_DB * wall_crossings(fw, np.repeat(model.tx_pos[j : j + 1, :2], len(xy), axis=0), xy)
    r = (
        model.p0[tx_idx][None]
        - 10 * PATH_LOSS_N * np.log10(np.maximum(d, 1.0))
        - walls
        - FLOOR_DB * np.abs(fl[:, None] - tx[None, :, 2])
        + shadow
        + TEMPORAL_SD * rng.standard_normal(d.shape)
        + offset
    )
    return r[0] if single else r


@dataclass
class WalkRadio:
    wifi: list[RfScan]
    ble: list[RfScan]
    rfid: list[AbsoluteFix]
    gps: list[AbsoluteFix]
    gps_sigma_random: list[float] = field(default_factory=list)  # per GPS fix: sigma of its random part e_r, m


def simulate_radio(
    model: RadioModel,
    walk: Walk,
    rng: np.random.Generator,
    device_model: str = "SIM PHONE",
    device_offset: float = 0.0,
    wifi_period: float = 3.5,
    gps_indoor_reach: float = 3.0,
) -> WalkRadio:
    world = model.world
    n_ap = len(world.aps)
    ap_idx = np.arange(n_ap)
    bc_idx = np.arange(n_ap, n_ap + len(world.beacons))
    wifi, ble, rfid, gps = [], [], [], []
    # WiFi scans, throttled, with Android-like caching: a reading can be up to 2 s old at scan time
    n_scans = max(0, int((walk.t1 - walk.t0) / wifi_period) + 2)
    ts = walk.t0 + float(rng.uniform(0, wifi_period)) + np.cumsum(np.concatenate([[0.0], wifi_period * rng.uniform(0.9, 1.1, n_scans)]))
    ts = ts[ts < walk.t1]
    if len(ts):
        pos, fl = walk.position_at(ts)
        R = np.round(rssi(model, ap_idx, pos, fl, rng, device_offset))
        ages = rng.uniform(0.0, 2.0, R.shape)
        ids = world.ap_ids
        freq = (world.ap_freq_mhz * 1e6).tolist()
        for t, row, age in zip(ts.tolist(), R.tolist(), ages.tolist()):
            heard = [j for j, v in enumerate(row) if v > -92.0]
            wifi.append(
                RfScan(
                    t,
                    Technology.WIFI,
                    {ids[j]: row[j] for j in heard},
                    {ids[j]: freq[j] for j in heard},
                    {ids[j]: age[j] for j in heard},
                    device_model,
                )
            )
    # BLE: one report per second of the beacons heard
    tb = np.arange(walk.t0 + 0.5, walk.t1, 1.0)
    if len(tb):
        pos, fl = walk.position_at(tb)
        R = np.round(rssi(model, bc_idx, pos, fl, rng, device_offset))
        ids = world.beacon_ids
        for t, row in zip(tb.tolist(), R.tolist()):
            heard = {ids[j]: v for j, v in enumerate(row) if v > -95.0}
            if heard:
                ble.append(RfScan(t, Technology.BLE, heard, device_model=device_model))
    # RFID at doors (Kourogi sec. 4: an active tag at hip height, ~0.6 m, detected within 1.5 m; the
    # fix is the reader's position with sigma 0.4 m). The range is in 3-D: with the reader in the door
    # frame at 2.0 m the horizontal reach is sqrt(1.5^2 - 1.4^2) = 0.54 m, so the fix's true error
    # (<= 0.54 m, ~0.27 m per axis) sits inside the 0.4 m it claims; walkers passing a door at a
    # corridor's width are not detected, those going through it are. At the walker's step events.
    reach = math.sqrt(max(RFID_RANGE**2 - (RFID_READER_H - RFID_TAG_H) ** 2, 0.0))
    if len(world.rfid) and walk.steps:
        st = np.array([[s.t, s.x, s.y, s.floor] for s in walk.steps])
        last = -np.inf
        for row in st:
            same = world.rfid[world.rfid[:, 2] == row[3]]
            if same.size == 0:
                continue
            d = np.linalg.norm(same[:, :2] - row[1:3], axis=1)
            k = int(np.argmin(d))
            if d[k] <= reach and row[0] - last > 5.0:
                rfid.append(AbsoluteFix(float(row[0]), same[k, :2].copy(), np.eye(2) * RFID_SIGMA**2, FixSource.RFID, world.floor_name(int(row[3]))))
                last = row[0]
    # GPS: outdoors and just inside the entrance (within gps_indoor_reach of the facade, 6 m of the
    # door), 1 Hz
    tg = np.arange(walk.t0, walk.t1, 1.0)
    pos, fl = walk.position_at(tg)
    inside = world.inside(pos)
    ent = np.asarray(world.entrance)
    facade = shapely.distance(world.plan.floors[0].outline.boundary, shapely.points(pos))
    ok = (fl == 0) & (~inside | ((facade <= gps_indoor_reach) & (np.linalg.norm(pos - ent, axis=1) <= 6.0 + gps_indoor_reach)))
    # Kourogi eq 8: p_gps = p + e_b + e_r. The biased error e_b (propagation delays) is locally constant
    # for one satellite set: a Gauss-Markov process, 2.5 m per axis, 60 s correlation time; the random
    # error e_r is white with sigma_r = 1.5 m x HDOP; plus 5 % multipath outliers (10-30 m).
    sig_b, tau = 2.5, 60.0
    e_b = sig_b * rng.standard_normal(2)
    t_prev = None
    gps_sr = []
    for t, p, ins in zip(tg[ok], pos[ok], inside[ok]):
        if t_prev is not None:
            a = math.exp(-(t - t_prev) / tau)
            e_b = a * e_b + sig_b * math.sqrt(1.0 - a * a) * rng.standard_normal(2)
        t_prev = t
        hdop = float(rng.uniform(0.8, 1.6)) if not ins else float(rng.uniform(3.0, 6.0))
        sig_r = 1.5 * hdop
        err = e_b + sig_r * rng.standard_normal(2)
        if rng.random() < 0.05:  # multipath outlier
            ang = rng.uniform(0, 2 * math.pi)
            err += rng.uniform(10.0, 30.0) * np.array([math.cos(ang), math.sin(ang)])
        gps.append(AbsoluteFix(float(t), p + err, np.eye(2) * (sig_b**2 + sig_r**2), FixSource.GPS, world.floor_name(0)))
        gps_sr.append(sig_r)
    return WalkRadio(wifi, ble, rfid, gps, gps_sr)
