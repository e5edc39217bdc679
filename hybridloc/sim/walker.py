"""Walkers: routes through a generated building and the truth of every step.

A walker has a speed (N(1.25, 0.15) m/s), a natural step length (N(0.65, 0.06) m) and a step-length
constant K of the bounce-height model L = K (mean |a_v| T^2)^(1/3) (N(0.70, 0.04): the real-walk fit,
with the 5 % spread between people of Weinberg's constant); the cadence is speed / step length. A
route visits a few random rooms along shortest paths of the walkable graph (stairs take 16 steps per
storey on two flights of 8 joined by a landing's half turn, a lift ride 10 s of standing), pauses
3-15 s at each destination (sometimes handling the phone), some routes return to their start (loops)
and some start outdoors in front of the entrance.

The truth is a list of :class:`TrueStep` (time, position after the step, floor, heading, length) and
the walking/standing/handling intervals; the IMU synthesis (:mod:`.imu`) and the radio (:mod:`.radio`)
both read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .building import STOREY, World

#: steps of one stair flight; a storey is two flights joined by a landing (16 steps of 0.22 m rise)
STEPS_PER_FLIGHT = 8


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
    length_k: float  # K of the bounce-height step model (hybridloc.pdr.steplength.BounceHeightLength)
    t0: float
    t1: float
    steps: list[TrueStep]
    start: tuple[float, float, int]
    pauses: list[tuple[float, float, bool]]  # (t_start, t_end, handling the phone)
    lift_rides: list[tuple[float, float]] = field(default_factory=list)
    loop: bool = False
    outdoor_start: bool = False

    def _arrays(self):
        if getattr(self, "_cache", None) is None or self._cache[0] != len(self.steps):
            ts = np.array([self.t0] + [s.t for s in self.steps])
            xs = np.array([self.start[0]] + [s.x for s in self.steps])
            ys = np.array([self.start[1]] + [s.y for s in self.steps])
            fs = np.array([self.start[2]] + [s.floor for s in self.steps])
            self._cache = (len(self.steps), ts, xs, ys, fs)
        return self._cache[1:]

    def position_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) positions and (N,) floor indices at times t (linear between step events)."""
        ts, xs, ys, fs = self._arrays()
        t = np.asarray(t, float)
        pos = np.column_stack([np.interp(t, ts, xs), np.interp(t, ts, ys)])
        k = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(ts) - 1)
        return pos, fs[k]


def _polyline(world: World, path: list[int]) -> list[tuple[float, float, int, str]]:
    return [(float(world.nodes[i, 0]), float(world.nodes[i, 1]), int(world.nodes[i, 2]), world.node_kind[i]) for i in path]


def simulate_walk(world: World, rng: np.random.Generator, minutes: float, walker: int = 0, t0: float = 1.7e9, close_loop: bool = False) -> Walk:
    """One walker for ``minutes``; with ``close_loop`` the walk always returns to its start after the
    time is up (a closed loop for return-to-start tests), otherwise 30 % of routes loop by chance."""
    speed = float(np.clip(rng.normal(1.25, 0.15), 0.8, 1.8))
    L = float(np.clip(rng.normal(0.65, 0.06), 0.5, 0.9))
    K = float(np.clip(rng.normal(0.70, 0.04), 0.57, 0.85))
    cadence = speed / L
    comp = world.component
    size = np.bincount(comp)
    # destinations in parts of the building big enough to walk in (a real plan's grid leaves islands)
    rooms_all = [i for i, k in enumerate(world.node_kind) if k == "room" and size[comp[i]] >= 0.05 * len(comp)] or [
        i for i, k in enumerate(world.node_kind) if k == "room"
    ]
    outdoor = rng.random() < 0.2
    start_node = world.outdoor_node if outdoor else int(rng.choice(rooms_all))
    rooms = [i for i in rooms_all if comp[i] == comp[start_node]] or rooms_all  # reachable from the start
    loop = close_loop or rng.random() < 0.3
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
    closing = False
    while t < t_end or (close_loop and not closing):
        if close_loop and t >= t_end and not closing:
            closing, targets = True, [start_node]  # time is up: head back to the start and stop there
            t_end = math.inf
        if not targets:
            if closing:
                break
            targets = [int(rng.choice(rooms)) for _ in range(int(rng.integers(2, 5)))]
            if loop:
                targets.append(start_node)
        dest = targets.pop(0)
        if dest == node:
            continue
        path = world.shortest_path(node, dest)
        pts = _polyline(world, path)
        # split the route into same-floor polylines joined by floor changes
        k = 0
        t_stop = math.inf if close_loop else t_end  # a closing walk finishes its route
        while k < len(pts) - 1 and t < t_stop:
            if pts[k][2] != pts[k + 1][2]:
                (_, _, fa, ka), (xb, yb, fb, _) = pts[k], pts[k + 1]
                if ka == "lift":  # ride: stand for 10 s per storey
                    dt = 10.0 * abs(fb - fa)
                    lifts.append((t, t + dt))
                    pauses.append((t, t + dt, False))
                    t += dt
                else:
                    # stairs: 16 steps per storey on switchback flights within the stairwell, two
                    # flights of 8 steps joined by a half turn on the landing
                    n = 16 * abs(fb - fa)
                    for j in range(n):
                        t += 1.0 / (0.8 * cadence) * float(rng.uniform(0.97, 1.03))
                        heading = math.pi / 2 if (j // STEPS_PER_FLIGHT) % 2 == 0 else -math.pi / 2
                        x, y = x + 0.29 * math.cos(heading), y + 0.29 * math.sin(heading)
                        steps.append(TrueStep(t, x, y, fa if j < n - 1 else fb, heading, 0.29, math.copysign(STOREY / 16, fb - fa)))
                fl = fb
                x, y = xb, yb
                k += 1
                continue
            j = k
            while j < len(pts) - 1 and pts[j + 1][2] == pts[k][2]:
                j += 1
            poly = np.array([[x, y]] + [[p[0], p[1]] for p in pts[k + 1 : j + 1]])
            seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
            arc = np.concatenate([[0.0], np.cumsum(seg)])
            total = float(arc[-1])
            if total > 1e-6:
                # People spread a leg evenly over whole steps: n = round(total / L) steps of total / n
                # (2 % jitter) along the polyline, so there are no tiny leftover steps.
                n_steps = max(1, int(round(total / L)))
                s_pos = 0.0
                for j_step in range(n_steps):
                    if t >= t_stop:
                        break
                    s_new = total if j_step == n_steps - 1 else min(total, s_pos + total / n_steps * float(rng.uniform(0.98, 1.02)))
                    nx, ny = float(np.interp(s_new, arc, poly[:, 0])), float(np.interp(s_new, arc, poly[:, 1]))
                    t += 1.0 / cadence * float(rng.uniform(0.97, 1.03))
                    heading = math.atan2(ny - y, nx - x)
                    steps.append(TrueStep(t, nx, ny, fl, heading, math.hypot(nx - x, ny - y), 0.0))
                    x, y, s_pos = nx, ny, s_new
            k = j
        node = dest
        pause = float(rng.uniform(3.0, 15.0))
        pauses.append((t, t + pause, bool(rng.random() < 0.3)))
        t += pause
    steps = [s for s in steps if s.t <= t_end]
    return Walk(
        walker,
        speed,
        L,
        K,
        t0,
        min(t, t_end) if math.isfinite(t_end) else t,
        steps,
        tuple(float(v) for v in world.nodes[start_node][:2]) + (int(world.nodes[start_node][2]),),
        pauses,
        lifts,
        loop,
        outdoor,
    )
