"""Radio measurements of a simulated walk: WiFi, BLE, RFID, GPS.

RSSI (dBm) of transmitter j at position p on floor f:

    P0_j - 10 n log10(max(d, 1 m)) - W * walls(j, p) - F * |f - f_j| + S_j(p) + e + o_device

* log-distance path loss (P0 -38 dBm at 1 m for 2.4 GHz, -45 dBm for 5 GHz, n = 2.2 inside the free
  corridor; walls add W = 4 dB each, counted on the floor plan; floors F = 15 dB each);
* S_j: spatially correlated shadowing, a Gaussian random field (random Fourier features) with
  sigma 4 dB and correlation length 3 m: the same place looks alike, nearby places look similar;
* e: temporal noise N(0, 2 dB); o_device: the phone model's offset;
* a reading exists above the detection threshold (-92 dBm WiFi, -95 dBm BLE).

Scan throttling: a WiFi scan every ``wifi_period`` s (3-4 s, Android's foreground rate; pass 30 for
Android 9's 4 scans per 2 minutes), a BLE report per beacon per second. RFID readers at doors detect
the walker within 1.5 m and give a fix with sigma 0.4 m (Kourogi et al.). GPS works outdoors and
within ``gps_indoor_reach`` m inside the entrance, with noise sigma = 3 m x HDOP and 5 % multipath
outliers of 10-30 m (Kourogi et al. sec. 3.1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..types import AbsoluteFix, FixSource, RfScan, Technology
from .building import STOREY, World, wall_crossings
from .walker import Walk

WALL_DB = 4.0
FLOOR_DB = 15.0
PATH_LOSS_N = 2.2
SHADOW_SD = 4.0
SHADOW_LENGTH = 3.0
TEMPORAL_SD = 2.0


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
    walls_db: np.ndarray  # (A + B, n_floors, ny, nx) wall attenuation from tx to grid cell on each floor


def make_radio_model(world: World, rng: np.random.Generator, n_terms: int = 32, grid: float = 1.0) -> RadioModel:
    tx = np.vstack([world.aps, world.beacons])
    n_tx = len(tx)
    w = rng.normal(0.0, 1.0 / SHADOW_LENGTH, (n_tx, n_terms, 2))
    b = rng.uniform(0, 2 * math.pi, (n_tx, n_terms))
    c = rng.normal(0.0, SHADOW_SD * math.sqrt(2.0 / n_terms), (n_tx, n_terms))
    p0 = np.concatenate([np.where(world.ap_freq_mhz < 3000, -38.0, -45.0), np.full(len(world.beacons), -59.0 + 0.0)])
    gx = np.arange(-15.0, world.width + 15.0 + grid, grid)
    gy = np.arange(-15.0, world.depth + 15.0 + grid, grid)
    X, Y = np.meshgrid(gx, gy)
    pts = np.column_stack([X.ravel(), Y.ravel()])
    walls_db = np.zeros((n_tx, world.n_floors, len(gy), len(gx)), np.float32)
    for j in range(n_tx):
        fj = int(tx[j, 2])
        walls = world.plan.floors[fj].walls
        nw = wall_crossings(walls, np.repeat(tx[j : j + 1, :2], len(pts), axis=0), pts)
        walls_db[j, :] = (WALL_DB * nw).reshape(len(gy), len(gx))[None]
    return RadioModel(world, w, b, c, p0, tx, gx, gy, walls_db)


def rssi(model: RadioModel, tx_idx: np.ndarray, xy: np.ndarray, floor: int, rng: np.random.Generator, offset: float = 0.0) -> np.ndarray:
    """Readings of transmitters ``tx_idx`` at one position (no detection threshold), dBm."""
    tx = model.tx_pos[tx_idx]
    dz = (floor - tx[:, 2]) * STOREY
    d = np.sqrt(np.sum((tx[:, :2] - xy) ** 2, axis=1) + dz**2)
    shadow = np.einsum("jk,jk->j", np.cos(np.einsum("jkd,d->jk", model.w[tx_idx], xy) + model.b[tx_idx]), model.c[tx_idx])
    ix = int(np.clip(np.searchsorted(model.grid_x, xy[0]), 0, len(model.grid_x) - 1))
    iy = int(np.clip(np.searchsorted(model.grid_y, xy[1]), 0, len(model.grid_y) - 1))
    walls = model.walls_db[tx_idx, min(floor, model.walls_db.shape[1] - 1), iy, ix]
    return (model.p0[tx_idx] - 10 * PATH_LOSS_N * np.log10(np.maximum(d, 1.0)) - walls - FLOOR_DB * np.abs(floor - tx[:, 2])
            + shadow + TEMPORAL_SD * rng.standard_normal(len(tx_idx)) + offset)


@dataclass
class WalkRadio:
    wifi: list[RfScan]
    ble: list[RfScan]
    rfid: list[AbsoluteFix]
    gps: list[AbsoluteFix]


def simulate_radio(model: RadioModel, walk: Walk, rng: np.random.Generator, device_model: str = "SIM PHONE", device_offset: float = 0.0,
                   wifi_period: float = 3.5, gps_indoor_reach: float = 3.0) -> WalkRadio:
    world = model.world
    n_ap = len(world.aps)
    ap_idx = np.arange(n_ap)
    bc_idx = np.arange(n_ap, n_ap + len(world.beacons))
    wifi, ble, rfid, gps = [], [], [], []
    # WiFi scans, throttled, with Android-like caching: a reading can be up to 2 s old at scan time
    t = walk.t0 + float(rng.uniform(0, wifi_period))
    while t < walk.t1:
        pos, fl = walk.position_at(np.array([t]))
        r = rssi(model, ap_idx, pos[0], int(fl[0]), rng, device_offset)
        heard = np.flatnonzero(r > -92.0)
        age = rng.uniform(0.0, 2.0, len(heard))
        wifi.append(RfScan(t, Technology.WIFI, {world.ap_ids[j]: float(np.round(r[j])) for j in heard},
                           {world.ap_ids[j]: float(world.ap_freq_mhz[j]) * 1e6 for j in heard}, {world.ap_ids[j]: float(a) for j, a in zip(heard, age)}, device_model))
        t += wifi_period * float(rng.uniform(0.9, 1.1))
    # BLE: one report per second of the beacons heard
    for t in np.arange(walk.t0 + 0.5, walk.t1, 1.0):
        pos, fl = walk.position_at(np.array([t]))
        r = rssi(model, bc_idx, pos[0], int(fl[0]), rng, device_offset)
        heard = np.flatnonzero(r > -95.0)
        if heard.size:
            ble.append(RfScan(float(t), Technology.BLE, {world.beacon_ids[j]: float(np.round(r[j])) for j in heard}, device_model=device_model))
    # RFID at doors (Kourogi: range ~1.5 m, sigma 0.4 m), at the walker's step events
    if len(world.rfid) and walk.steps:
        st = np.array([[s.t, s.x, s.y, s.floor] for s in walk.steps])
        last = -np.inf
        for row in st:
            same = world.rfid[world.rfid[:, 2] == row[3]]
            if same.size == 0:
                continue
            d = np.linalg.norm(same[:, :2] - row[1:3], axis=1)
            k = int(np.argmin(d))
            if d[k] <= 1.5 and row[0] - last > 5.0:
                rfid.append(AbsoluteFix(float(row[0]), same[k, :2].copy(), np.eye(2) * 0.4**2, FixSource.RFID, world.floor_name(int(row[3]))))
                last = row[0]
    # GPS: outdoors (y < 0) and just inside the entrance, 1 Hz
    for t in np.arange(walk.t0, walk.t1, 1.0):
        pos, fl = walk.position_at(np.array([t]))
        x, y = pos[0]
        if int(fl[0]) != 0:
            continue
        inside = y > 0.0
        if inside and (y > gps_indoor_reach or abs(x - world.entrance[0]) > 6.0):
            continue
        hdop = float(rng.uniform(0.8, 1.6)) if not inside else float(rng.uniform(3.0, 6.0))
        sigma = 3.0 * hdop
        err = sigma * rng.standard_normal(2)
        if rng.random() < 0.05:  # multipath outlier
            ang = rng.uniform(0, 2 * math.pi)
            err += rng.uniform(10.0, 30.0) * np.array([math.cos(ang), math.sin(ang)])
        gps.append(AbsoluteFix(float(t), pos[0] + err, np.eye(2) * sigma**2, FixSource.GPS, world.floor_name(0)))
    return WalkRadio(wifi, ble, rfid, gps)
