"""Placing one walk on a radio map: a whole-walk consensus of its scans' fixes and the floor plan.

A single WiFi fix in a mall is often in the wrong corridor (slam.md 3.2: single-scan similarity is a
weak signal), and a single 30 s walk does not place on the plan alone (slam.md 3.4). Together they do
better: the walk's dead-reckoned shape q_i (heading nearly absolute, slam.md 3.1) is known up to a
similarity x -> T x + t close to the identity, so the fixes z_i of its scans must agree on ONE t.

Score of a placement (T, t), a robust log-likelihood (Cauchy in each fix, tempered walkable term):

    L(T, t) = - sum_i log(1 + |T q_i + t - z_i|^2 / (c sigma_i)^2)
              + w_plan * sum_k max(-0.5 (d(T s_k + t) / sigma_w)^2, floor) / K            (s_k: step points)

Search: each fix proposes t = z_i - T q_i for every T on a small grid of rotations and scales
(RANSAC-like, exhaustive: a walk has ~15 fixes); the best proposals are refined by Gauss-Newton-free
local grid steps. The walk is placed when the best placement is supported by enough fixes (within
``support_m``) and no placement more than ``mode_sep_m`` away scores within ``ambiguity`` of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class RegisterConfig:
    rotations_deg: tuple[float, ...] = (-10.0, -5.0, 0.0, 5.0, 10.0)
    scales: tuple[float, ...] = (0.85, 0.95, 1.05)
    #: Cauchy width in units of each fix's sd
    c: float = 1.0
    #: walkable-area term: its weight (per walk, the step term is averaged) and the distance sd, m
    plan_weight: float = 4.0
    plan_sigma_m: float = 1.0
    plan_floor: float = -8.0
    #: a fix supports a placement when within this distance of it, m
    support_m: float = 6.0
    min_support: int = 3
    min_support_share: float = 0.4
    #: another mode (farther than mode_sep_m) within this log-likelihood of the best: ambiguous
    mode_sep_m: float = 10.0
    ambiguity: float = 1.0
    #: local refinement steps around the best proposals, m
    refine_m: tuple[float, ...] = (2.0, 1.0, 0.5)


@dataclass
class Registration:
    T: np.ndarray  # (2, 2) scale * rotation
    t: np.ndarray  # (2,)
    score: float
    runner_up: float
    support: int
    n_fixes: int
    placed: bool
    reason: str = ""


def _rot(deg: float, s: float) -> np.ndarray:
    a = math.radians(deg)
    return s * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def register_walk(
    q_fix: np.ndarray, z: np.ndarray, sd: np.ndarray, steps: np.ndarray | None = None, field=None, cfg: RegisterConfig | None = None
) -> Registration:
    """Place a walk (module docstring). ``q_fix`` (n, 2): walk-frame positions of the scans that have
    fixes ``z`` (n, 2) with sd ``sd`` (n,) m; ``steps`` (m, 2): walk-frame step points for the plan term."""
    cfg = cfg or RegisterConfig()
    q_fix, z = np.asarray(q_fix, float).reshape(-1, 2), np.asarray(z, float).reshape(-1, 2)
    sd = np.maximum(np.asarray(sd, float).reshape(-1), 0.5)
    n = len(z)
    if n < cfg.min_support:
        return Registration(np.eye(2), np.zeros(2), -math.inf, -math.inf, 0, n, False, "too few fixes")
    S = None
    if steps is not None and field is not None and len(steps):
        S = np.asarray(steps, float)[:: max(1, len(steps) // 60)]  # <= ~60 points: the shape, not every step

    def score(T: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Scores of many translations t (k, 2) for one T."""
        p = q_fix @ T.T  # (n, 2)
        r = p[None, :, :] + t[:, None, :] - z[None, :, :]
        e2 = (r**2).sum(-1) / (cfg.c * sd[None, :]) ** 2
        out = -np.log1p(e2).sum(1)
        if S is not None:
            ps = (S @ T.T)[None, :, :] + t[:, None, :]
            d, _ = field(ps.reshape(-1, 2))
            ll = np.maximum(-0.5 * (d.reshape(len(t), -1) / cfg.plan_sigma_m) ** 2, cfg.plan_floor)
            out = out + cfg.plan_weight * ll.mean(1)
        return out

    best: list[tuple[float, np.ndarray, np.ndarray]] = []  # (score, T, t)
    for deg in cfg.rotations_deg:
        for s in cfg.scales:
            T = _rot(deg, s)
            prop = z - q_fix @ T.T  # each fix's translation
            sc = score(T, prop)
            for k in np.argsort(-sc)[:3]:
                best.append((float(sc[k]), T, prop[k]))
    best.sort(key=lambda b: -b[0])
    # refine the best few by local grid steps
    refined = []
    for sc0, T, t0 in best[:6]:
        t, sc = t0.copy(), sc0
        for h in cfg.refine_m:
            g = np.array([[dx, dy] for dx in (-h, 0.0, h) for dy in (-h, 0.0, h)])
            for _ in range(6):
                cand = t + g
                v = score(T, cand)
                k = int(np.argmax(v))
                if v[k] <= sc + 1e-9:
                    break
                t, sc = cand[k], float(v[k])
        refined.append((sc, T, t))
    refined.sort(key=lambda b: -b[0])
    sc, T, t = refined[0]
    # runner-up: the best proposal whose placement moves the walk's centre by more than mode_sep_m
    c0 = q_fix.mean(0)
    centre = T @ c0 + t
    others = [b[0] for b in refined[1:] + best if np.linalg.norm(b[1] @ c0 + b[2] - centre) > cfg.mode_sep_m]
    runner = max(others) if others else -math.inf
    res = np.linalg.norm(q_fix @ T.T + t - z, axis=1)
    support = int((res <= cfg.support_m).sum())
    placed, reason = True, ""
    if support < max(cfg.min_support, math.ceil(cfg.min_support_share * n)):
        placed, reason = False, f"support {support} of {n} fixes"
    elif runner > sc - cfg.ambiguity:
        placed, reason = False, "ambiguous"
    return Registration(T, t, sc, runner, support, n, placed, reason)
