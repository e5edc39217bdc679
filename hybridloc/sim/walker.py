"""Walkers: routes through a generated building and the truth of every step.

A walker has a speed (N(1.3, 0.15) m/s), a natural step length (N(0.70, 0.06) m) and a Weinberg
constant (N(0.37, 0.02)); the cadence is speed / step length. A route visits a few random rooms along
shortest paths of the walkable graph (stairs take ~16 steps per storey, a lift ride 10 s of standing),
pauses 3-15 s at each destination (sometimes handling the phone), some routes return to their start
(loops) and some start outdoors in front of the entrance.

The truth is a list of :class:`TrueStep` (time, position after the step, floor, heading, length) and
the walking/standing/handling intervals; the IMU synthesis (:mod:`.imu`) and the radio (:mod:`.radio`)
both read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .building import STOREY, World


@dataclass(frozen=True)
class TrueStep:
    t: float
    x: float
    y: float
    floor: int
    heading: float  # rad, CCW from East
    length: float  # m (horizontal)
    dz: float  # m, height change (stairs)


@dataclass
class Walk:
    walker: int
    speed: float
    step_length: float
    weinberg_k: float
    t0: float
    t1: float
    steps: list[TrueStep]
    start: tuple[float, float, int]
    pauses: list[tuple[float, float, bool]]  # (t_start, t_end, handling the phone)
    lift_rides: list[tuple[float, float]] = field(default_factory=list)
    loop: bool = False
    outdoor_start: bool = False

    def position_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) positions and (N,) floor indices at times t (linear between step events)."""
        ts = np.array([self.t0] + [s.t for s in self.steps])
        xs = np.array([self.start[0]] + [s.x for s in self.steps])
        ys = np.array([self.start[1]] + [s.y for s in self.steps])
        fs = np.array([self.start[2]] + [s.floor for s in self.steps])
        t = np.asarray(t, float)
        pos = np.column_stack([np.interp(t, ts, xs), np.interp(t, ts, ys)])
        k = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 1)
        return pos, fs[k]


def _polyline(world: World, path: list[int]) -> list[tuple[float, float, int, str]]:
    return [(float(world.nodes[i, 0]), float(world.nodes[i, 1]), int(world.nodes[i, 2]), world.node_kind[i]) for i in path]


def simulate_walk(world: World, rng: np.random.Generator, minutes: float, walker: int = 0, t0: float = 1.7e9) -> Walk:
    speed = float(np.clip(rng.normal(1.3, 0.15), 0.8, 1.8))
    L = float(np.clip(rng.normal(0.70, 0.06), 0.5, 0.9))
    K = float(np.clip(rng.normal(0.37, 0.02), 0.3, 0.45))
    cadence = speed / L
    rooms = [i for i, k in enumerate(world.node_kind) if k == "room"]
    outdoor = rng.random() < 0.2
    start_node = world.outdoor_node if outdoor else int(rng.choice(rooms))
    loop = rng.random() < 0.3
    x, y, fl = (float(v) for v in world.nodes[start_node])
    fl = int(fl)
    t = t0 + float(rng.uniform(2.0, 5.0))  # standing still at the start (filters settle)
    steps: list[TrueStep] = []
    pauses = [(t0, t, False)]
    lifts: list[tuple[float, float]] = []
    t_end = t0 + minutes * 60.0
    node = start_node
    heading = 0.0
    targets: list[int] = []
    while t < t_end:
        if not targets:
            targets = [int(rng.choice(rooms)) for _ in range(int(rng.integers(2, 5)))]
            if loop:
                targets.append(start_node)
        dest = targets.pop(0)
        if dest == node:
            continue
        path = world.shortest_path(node, dest)
        pts = _polyline(world, path)
        for (xa, ya, fa, ka), (xb, yb, fb, kb) in zip(pts[:-1], pts[1:]):
            if t >= t_end:
                break
            if fa != fb:
                if ka == "lift":  # ride: stand for 10 s per storey
                    dt = 10.0 * abs(fb - fa)
                    lifts.append((t, t + dt))
                    pauses.append((t, t + dt, False))
                    t += dt
                    fl = fb
                    continue
                # stairs: 16 steps per storey in place horizontally (a compact stairwell), 0.29 m short steps
                n = 16 * abs(fb - fa)
                for k in range(n):
                    t += 1.0 / (0.8 * cadence) * float(rng.uniform(0.97, 1.03))
                    heading = math.pi / 2 if k % 2 == 0 else -math.pi / 2  # switchback flights
                    dx, dy = 0.29 * math.cos(heading), 0.29 * math.sin(heading)
                    x, y = x + dx, y + dy
                    f_now = fa if k < n - 1 else fb
                    steps.append(TrueStep(t, x, y, f_now, heading, 0.29, math.copysign(STOREY / 16, fb - fa)))
                fl = fb
                x, y = xb, yb
                continue
            seg = math.hypot(xb - x, yb - y)
            if seg < 1e-6:
                continue
            heading = math.atan2(yb - y, xb - x)
            n = max(1, int(round(seg / L)))
            for k in range(n):
                step_len = seg / n * float(rng.uniform(0.98, 1.02))
                t += 1.0 / cadence * float(rng.uniform(0.97, 1.03))
                x += step_len * math.cos(heading)
                y += step_len * math.sin(heading)
                steps.append(TrueStep(t, x, y, fl, heading, step_len, 0.0))
            x, y = xb, yb
        node = dest
        pause = float(rng.uniform(3.0, 15.0))
        pauses.append((t, t + pause, bool(rng.random() < 0.3)))
        t += pause
    steps = [s for s in steps if s.t <= t_end]
    return Walk(walker, speed, L, K, t0, min(t, t_end), steps, tuple(float(v) for v in world.nodes[start_node][:2]) + (int(world.nodes[start_node][2]),),
                pauses, lifts, loop, outdoor)
