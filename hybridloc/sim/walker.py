"""Walkers: routes through a generated building and the truth of every step.

A walker has a preferred speed (N(1.25, 0.15) m/s) and natural step length (N(0.65, 0.06) m); the
cadence is speed / step length. Their gait (:func:`com_excursion`):

* a leg length l (N(0.90, 0.05) m: about 0.53 of stature, adult stature ~N(1.71, 0.09) m; Winter,
  Biomechanics and Motor Control of Human Movement, segment proportions) and the inverted-pendulum
  correction factor c of Zijlstra and Hof (N(1.25, 0.08); see :data:`PENDULUM_CORRECTION`);
* a pace per route leg (to each destination): the speed times u, u log-normal (sd
  :data:`PACE_SD`), with the walk ratio (step length / cadence) kept, as people keep it across
  speeds (Sekiya and Nagasaki 1998, Gait & Posture 7: the walk ratio is nearly constant over a
  person's range of speeds): step length L sqrt(u), cadence sqrt(u) L / speed;
* steps that vary from one to the next (length CV :data:`STEP_LENGTH_CV`, time +-3 %, the body's
  vertical excursion CV :data:`BOUNCE_CV`: healthy adults' step-to-step variability is a few %).

Every true step carries the vertical excursion of the centre of mass (CoM) it makes, from the
inverted pendulum the stance leg is (:func:`com_excursion`); the phone's IMU (:mod:`.imu`) turns it
into the vertical bounce at the step's frequency, so the step length follows the bounce as
Weinberg-type step models assume (and as loosely as on real walkers).

A route visits a few random rooms along shortest paths of the walkable graph (stairs take 16 steps
per storey on two flights of 8 joined by a landing's half turn, a lift ride 10 s of standing), pauses
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
    bounce: float = 0.0  # m, vertical excursion of the centre of mass over the step, trough to crest


#: Zijlstra and Hof (2003, Gait & Posture 18, "Assessment of spatio-temporal gait parameters from
#: trunk accelerations during human walking"): the compass-gait inverted pendulum s = 2 sqrt(2 l h - h^2)
#: underestimates step length (pelvic rotation, the stance knee, the foot's roll-over lengthen the step
#: for a given rise of the CoM); their step lengths needed a correction factor of about 1.25, which
#: differs between people (spread here 0.08).
PENDULUM_CORRECTION = (1.25, 0.08)
#: m, leg length (greater trochanter to floor): mean, sd between adults
LEG_LENGTH_M = (0.90, 0.05)
#: relative sd of a walker's pace from one route leg to the next (log-normal)
PACE_SD = 0.10
#: Hz: a faster pace than this is not walking (brisk walking reaches ~2.5-3 steps/s)
MAX_CADENCE_HZ = 3.0
#: step-to-step coefficient of variation of step length (healthy adults' 2-3 %)
STEP_LENGTH_CV = 0.025
#: step-to-step coefficient of variation of the CoM's vertical excursion
BOUNCE_CV = 0.08


def com_excursion(step_length, leg_length, correction=PENDULUM_CORRECTION[0]):
    """Vertical excursion h (m) of the centre of mass over a step of ``step_length`` (m).

    The stance leg is an inverted pendulum of length l: from double support (the CoM lowest, the legs
    at +-s/2 from it) to mid-stance (the CoM above the foot, highest) the hip rises by
    h = l - sqrt(l^2 - (s / 2)^2), i.e. s = 2 sqrt(2 l h - h^2) (Zijlstra and Hof 2003, eq. 1), with
    their correction factor c on the step length: h = l - sqrt(l^2 - (s / (2 c))^2). For small steps
    h ~ s^2 / (8 l c^2). Moving up and down by h once per step of period T, the CoM's vertical
    acceleration swings by h (2 pi / T)^2 peak to peak; with the walk ratio r = s / f kept, that is
    pi^2 s^4 / (2 l c^2 r^2), so s = (2 l c^2 r^2 / pi^2)^(1/4) (a_max - a_min)^(1/4): Weinberg's
    fourth root, with a constant that depends on the walker (Harle's survey sec. V-A: Weinberg's
    relation takes the leg's angle as constant "although it is actually related to the leg length")."""
    half = np.asarray(step_length, float) / (2.0 * correction)
    return leg_length - np.sqrt(np.maximum(leg_length**2 - half**2, 0.0))


@dataclass
class Walk:
    walker: int
    speed: float
    step_length: float
    #: K of the bounce-height step model (hybridloc.pdr.steplength.BounceHeightLength) at the walker's
    #: natural step with a sinusoidal bounce: L = K (mean |a_v| T^2)^(1/3), mean |a_v| = h (2 pi / T)^2 / pi,
    #: so K = L / (4 pi h)^(1/3); derived from the gait, for reference (the IMU no longer uses it)
    length_k: float
    t0: float
    t1: float
    steps: list[TrueStep]
    start: tuple[float, float, int]
    pauses: list[tuple[float, float, bool]]  # (t_start, t_end, handling the phone)
    lift_rides: list[tuple[float, float]] = field(default_factory=list)
    loop: bool = False
    outdoor_start: bool = False
    leg_length: float = LEG_LENGTH_M[0]  # m
    pendulum_correction: float = PENDULUM_CORRECTION[0]

    @property
    def natural_bounce(self) -> float:
        """m: the CoM's vertical excursion at the walker's natural step (:func:`com_excursion`)."""
        return float(com_excursion(self.step_length, self.leg_length, self.pendulum_correction))

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
    leg = float(np.clip(rng.normal(*LEG_LENGTH_M), 0.75, 1.05))
    corr = float(np.clip(rng.normal(*PENDULUM_CORRECTION), 1.0, 1.5))
    cadence = speed / L

    def bounce(length: float) -> float:
        return float(com_excursion(length, leg, corr)) * float(np.exp(BOUNCE_CV * rng.standard_normal()))

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
        # this leg's pace u (speed x u): step length L sqrt(u) and cadence sqrt(u) x the natural one, so the
        # walk ratio (step length / cadence) stays the walker's
        pace = math.sqrt(float(np.exp(PACE_SD * rng.standard_normal())))
        # (a leg never steps faster than MAX_CADENCE_HZ, nor than the walker's own cadence if that is faster)
        L_leg, cadence_leg = L * pace, min(cadence * pace, max(cadence, MAX_CADENCE_HZ))
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
                        # the body rises and falls over each stair step like a natural step (its own bounce)
                        steps.append(TrueStep(t, x, y, fa if j < n - 1 else fb, heading, 0.29, math.copysign(STOREY / 16, fb - fa), bounce(L)))
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
                # People spread a leg evenly over whole steps: n = round(total / L) steps along the
                # polyline, each total / n times its own variation (CV STEP_LENGTH_CV, renormalised to
                # the leg), so there are no tiny leftover steps.
                n_steps = max(1, int(round(total / L_leg)))
                w = np.clip(1.0 + STEP_LENGTH_CV * rng.standard_normal(n_steps), 0.9, 1.1)
                s_ends = total * np.cumsum(w) / w.sum()
                s_ends[-1] = total
                dts = rng.uniform(0.97, 1.03, n_steps) / cadence_leg
                t_after = t + np.cumsum(dts)
                n_keep = int(np.searchsorted(t_after - dts, t_stop, side="left"))  # steps begun before t_stop
                if n_keep:
                    nx = np.interp(s_ends[:n_keep], arc, poly[:, 0])
                    ny = np.interp(s_ends[:n_keep], arc, poly[:, 1])
                    px, py = np.concatenate([[x], nx[:-1]]), np.concatenate([[y], ny[:-1]])
                    lengths = np.hypot(nx - px, ny - py)
                    headings = np.arctan2(ny - py, nx - px)
                    h = com_excursion(lengths, leg, corr) * np.exp(BOUNCE_CV * rng.standard_normal(n_keep))
                    steps.extend(
                        TrueStep(ti, xi, yi, fl, hi, li, 0.0, bi)
                        for ti, xi, yi, hi, li, bi in zip(
                            t_after[:n_keep].tolist(), nx.tolist(), ny.tolist(), headings.tolist(), lengths.tolist(), h.tolist()
                        )
                    )
                    t, x, y = float(t_after[n_keep - 1]), float(nx[-1]), float(ny[-1])
                    heading = float(headings[-1])
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
        L / (4 * math.pi * float(com_excursion(L, leg, corr))) ** (1.0 / 3.0),
        t0,
        min(t, t_end) if math.isfinite(t_end) else t,
        steps,
        tuple(float(v) for v in world.nodes[start_node][:2]) + (int(world.nodes[start_node][2]),),
        pauses,
        lifts,
        loop,
        outdoor,
        leg,
        corr,
    )
