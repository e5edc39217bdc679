"""Placing a rigid group of points (a connected component of walks) on the floor plan.

A component of the crowd graph is solved in its own frame; the floor plan alone can place it when it is
large enough that only one place on the floor takes its shape (shared-notes slam.md 3.4-3.5, 4.5). The
search maximises the summed walkable log-likelihood (:meth:`.floorplan.WalkableField.log_likelihood`)

    S(T, t) = sum_i w_i log L(T p_i + t),   T = s R(theta)

over a similarity: rotations ``rotations_deg`` (heading is nearly absolute, slam.md 3.1: -10..10 deg),
scales ``scales`` (the PDR length scale, 0.9-1.1) and every translation on a ``grid``-m lattice. For each
(theta, s) the points are binned on the lattice into a weight image C and the translation scores for all
lattice offsets at once are the cross-correlation of the coarse log-likelihood raster with C
(by FFT): S[k] = sum_a C[a] L[k + a]. The lattice's local maxima over all
(theta, s) are the candidate placements; the best few, kept when they are ``min_separation`` m apart (the
root-mean-square displacement of the points between two placements), are refined on the fine field by a
local search (translation +-grid/2 in grid/4 steps, theta and s +-half their search step) and scored
exactly.

Ambiguity (do not anchor): the best and the runner-up mode - the best placement at least
``min_separation`` m away - differ by less than ``min_log_ratio`` in summed log-likelihood (a likelihood
ratio below exp(min_log_ratio)), or the best placement itself fits badly (mean log-likelihood per unit
weight below ``min_mean_fit``: most points off the walkable area). A short straight walk fits many
corridors equally well and is ambiguous; a large group has one place. The two thresholds are chosen in
``benchmarks/bench_anchoring.py`` across site1's floors.

Weights: the log-likelihoods of points 1 m apart along a path are not independent; pass for each point
the metres of path it stands for (default 1: points about 1 m apart) so the score, and the threshold on
it, do not depend on how densely the caller samples the walks.
"""

from __future__ import annotations

import copy
import hashlib
import math
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sp_fft
from scipy import ndimage

from .floorplan import WalkableField

#: Rotations searched, degrees: the per-walk heading deviation is median 5.4 deg, p90 15.7 deg, and a
#: group averages it (slam.md 3.1).
DEFAULT_ROTATIONS_DEG = tuple(float(a) for a in np.arange(-10.0, 10.01, 2.5))
#: Global length scales searched (PDR scale median 0.89, IQR 0.81-0.97, slam.md 3.1; a group carries
#: the crowd's mean).
DEFAULT_SCALES = (0.9, 0.95, 1.0, 1.05, 1.1)
#: Two placements are different modes when the points move this far (RMS) between them, m.
MIN_SEPARATION = 5.0
#: The best mode must beat the runner-up by this summed log-likelihood (weights in metres of path).
#: benchmarks/bench_anchoring.py on site1 (true group shapes, 20 groups per floor and size): a wrong best
#: mode never led its runner-up by more than 0 (a wrong place ties with another), on every floor; at 20
#: no single walk and 18 % of 5-walk groups are claimed, 92 % of 15-walk groups (F1 75 %, F2 and F3
#: 100 %), none wrongly. Lower thresholds claim a little more (5: 38 % and 95 %); real components carry
#: drift that the true shapes lack, so the margin is kept.
MIN_LOG_RATIO = 20.0
#: The best mode's mean log-likelihood per metre of path must be at least this (-0.5: on average
#: within 1 sigma of the walkable area).
MIN_MEAN_FIT = -0.5
#: Searches remembered per floor field (least recently used dropped first). A batch re-solve searches
#: every relative component of a floor once per solve (the first and each EM round) and again at the
#: next batch, mostly with the very same points: on site1's eval crowd the search was 31 % of the
#: SLAM child's time. The search is a pure function of its inputs, so a remembered answer is the
#: answer (:func:`anchor_points`).
MEMO_SIZE = 4096


@dataclass
class Anchoring:
    """A placement of a component on the floor: ``p_site = T @ p + t``.

    Attributes
    ----------
    T : ndarray (2, 2)
        Similarity (scale * rotation), component frame -> site frame.
    t : ndarray (2,)
        Translation, m.
    score : float
        Summed walkable log-likelihood of the best placement.
    runner_up : float
        The same for the best placement at least ``min_separation`` m away (-inf when none).
    ambiguous : bool
        Do not anchor: the runner-up is within the likelihood-ratio threshold, or the best fits badly.
    modes : list of (T, t, score)
        The top modes, best first, each ``min_separation`` m from the others.
    mean_fit : float
        ``score`` per unit weight.
    """

    T: np.ndarray
    t: np.ndarray
    score: float
    runner_up: float
    ambiguous: bool
    modes: list = field(default_factory=list)
    mean_fit: float = 0.0

    @property
    def rotation(self) -> float:
        """Rotation angle of T, rad."""
        return math.atan2(self.T[1, 0], self.T[0, 0])

    @property
    def scale(self) -> float:
        return math.hypot(self.T[0, 0], self.T[1, 0])

    def apply(self, p) -> np.ndarray:
        """Component-frame points (m, 2) -> site frame."""
        return np.asarray(p, float).reshape(-1, 2) @ self.T.T + self.t


def _similarity(theta: float, s: float) -> np.ndarray:
    c, si = math.cos(theta), math.sin(theta)
    return s * np.array([[c, -si], [si, c]])


def _rms_apart(P0: np.ndarray, a: tuple, b: tuple) -> float:
    """RMS displacement of the (centred) points between placements a = (T, t) and b."""
    d = P0 @ (a[0] - b[0]).T + (a[1] - b[1])
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _distinct(P0: np.ndarray, cands: list, min_separation: float, limit: int) -> list:
    """Greedy non-maximum suppression: candidates (score, T, t) sorted best first, kept when at least
    ``min_separation`` m (RMS) from every kept one."""
    kept: list = []
    for c in cands:
        if all(_rms_apart(P0, (c[1], c[2]), (k[1], k[2])) >= min_separation for k in kept):
            kept.append(c)
            if len(kept) >= limit:
                break
    return kept


def anchor_points(
    points,
    field: WalkableField,
    weights=None,
    rotations_deg=DEFAULT_ROTATIONS_DEG,
    scales=DEFAULT_SCALES,
    grid: float = 1.0,
    *,
    sigma: float = 1.0,
    floor: float = -8.0,
    min_separation: float = MIN_SEPARATION,
    min_log_ratio: float = MIN_LOG_RATIO,
    min_mean_fit: float = MIN_MEAN_FIT,
    n_modes: int = 3,
    peaks_per_pose: int = 8,
) -> Anchoring:
    """Search the similarity placing ``points`` (n, 2, component frame, m) best on ``field`` (module
    docstring). ``weights`` (n,): metres of path each point stands for (default 1).

    The answer depends on nothing but the arguments, so the field remembers the last
    :data:`MEMO_SIZE` searches (keyed by a digest of the points, the weights and every setting) and
    returns a copy of a remembered answer instead of searching again."""
    P = np.asarray(points, float).reshape(-1, 2)
    if len(P) == 0:
        raise ValueError("anchor_points: no points")
    w = np.ones(len(P)) if weights is None else np.asarray(weights, float).reshape(-1)
    if w.shape != (len(P),) or (w < 0).any() or w.sum() <= 0:
        raise ValueError("anchor_points: weights must be (n,) non-negative with a positive sum")
    rots = np.radians(np.asarray(rotations_deg, float).reshape(-1))
    scs = np.asarray(scales, float).reshape(-1)
    settings = (grid, sigma, floor, min_separation, min_log_ratio, min_mean_fit, n_modes, peaks_per_pose)
    h = hashlib.blake2b(digest_size=20)
    for a in (P, w, rots, scs, np.asarray(settings, float)):
        h.update(np.ascontiguousarray(a, float).tobytes())
        h.update(len(a).to_bytes(8, "little"))
    key = h.digest()
    memo: OrderedDict = field.__dict__.setdefault("_anchor_memo", OrderedDict())
    hit = memo.get(key)
    if hit is not None:
        try:
            memo.move_to_end(key)
        except KeyError:  # another thread dropped it meanwhile: the answer in hand stands
            pass
        return copy.deepcopy(hit)
    an = _search(P, w, field, rots, scs, grid, sigma, floor, min_separation, min_log_ratio, min_mean_fit, n_modes, peaks_per_pose)
    memo[key] = copy.deepcopy(an)
    while len(memo) > MEMO_SIZE:
        try:
            memo.popitem(last=False)
        except KeyError:
            break
    return an


def _search(P, w, field, rots, scs, grid, sigma, floor, min_separation, min_log_ratio, min_mean_fit, n_modes, peaks_per_pose) -> Anchoring:
    """The search of :func:`anchor_points` (module docstring), its arguments checked."""
    c = (w[:, None] * P).sum(0) / w.sum()
    P0 = P - c  # search about the centroid: rotation and scale then barely move it
    L, lx0, ly0 = field.log_likelihood_raster(grid, sigma, floor)
    reach = float(np.max(np.hypot(P0[:, 0], P0[:, 1]))) * float(scs.max()) if len(P0) else 0.0
    pad = int(math.ceil(reach / grid)) + 2  # placements partly off the raster stay possible (at the floor value)
    Lp = np.pad(L, pad, constant_values=floor)
    px0, py0 = lx0 - pad * grid, ly0 - pad * grid
    # circular cross-correlation by FFT: with a transform at least as large as Lp, the offsets k where
    # C fits inside Lp (k + a < Lp.shape) never wrap, so S[k] = irfft2(F(Lp) conj(F(C)))[k] there
    shape = tuple(sp_fft.next_fast_len(n, real=True) for n in Lp.shape)
    F_L = sp_fft.rfft2(Lp, s=shape)
    nbh = max(3, int(round(min_separation / grid)) | 1)  # local-maximum window, odd

    cands = []  # (score, T, t) in the caller's frame: p_site = T p + t
    for th in rots:
        for s in scs:
            T = _similarity(float(th), float(s))
            Q = P0 @ T.T
            qmin = Q.min(0)
            a = np.rint((Q - qmin) / grid).astype(np.int64)
            C = np.zeros((int(a[:, 1].max()) + 1, int(a[:, 0].max()) + 1))
            np.add.at(C, (a[:, 1], a[:, 0]), w)
            S = sp_fft.irfft2(F_L * np.conj(sp_fft.rfft2(C, s=shape)), s=shape)  # S[k] = sum_a C[a] Lp[k + a]
            S = S[: Lp.shape[0] - C.shape[0] + 1, : Lp.shape[1] - C.shape[1] + 1]
            peaks = (S == ndimage.maximum_filter(S, size=nbh, mode="nearest")) & (S > S.min())
            ky, kx = np.nonzero(peaks)
            if len(ky) == 0:
                ky, kx = np.unravel_index([int(np.argmax(S))], S.shape)
            order = np.argsort(-S[ky, kx])[:peaks_per_pose]
            for k in order:
                # lattice node (k + a) is where point Q - qmin + a*grid lands: t_search = node0 - qmin
                t_search = np.array([px0 + kx[k] * grid, py0 + ky[k] * grid]) - qmin
                cands.append((float(S[ky[k], kx[k]]), T, t_search - T @ c))
    cands.sort(key=lambda x: -x[0])
    coarse = _distinct(P0 + c, cands, min_separation, max(2 * n_modes, 6))

    # refine each coarse mode on the fine field
    d_rot = float(np.min(np.diff(np.sort(rots)))) if len(rots) > 1 else 0.0
    d_sc = float(np.min(np.diff(np.sort(scs)))) if len(scs) > 1 else 0.0
    offs = np.arange(-0.5 * grid, 0.5 * grid + 1e-9, 0.25 * grid)
    shifts = np.stack(np.meshgrid(offs, offs), axis=-1).reshape(-1, 2)
    refined = []
    for _, T, t in coarse:
        th0, s0 = math.atan2(T[1, 0], T[0, 0]), math.hypot(T[0, 0], T[1, 0])
        best = (-math.inf, T, t)
        for th in (th0 - d_rot / 2, th0, th0 + d_rot / 2) if d_rot else (th0,):
            for s in (s0 - d_sc / 2, s0, s0 + d_sc / 2) if d_sc else (s0,):
                T2 = _similarity(th, s)
                t2 = t + (T - T2) @ c  # keep the centroid where the coarse mode put it
                base = P @ T2.T + t2
                ll = field.log_likelihood((base[None, :, :] + shifts[:, None, :]).reshape(-1, 2), sigma, floor)
                sc = ll.reshape(len(shifts), len(P)) @ w
                top = float(sc.max())
                shift = shifts[int(np.argmax(sc))]
                # inside the walkable area the likelihood is flat: of a plateau of equal placements take
                # its centre (when it is on the plateau too), not the first one enumerated
                mid = shifts[sc >= top - 1e-9].mean(0)
                if float(w @ field.log_likelihood(base + mid, sigma, floor)) >= top - 1e-9:
                    shift = mid
                if top > best[0]:
                    best = (top, T2, t2 + shift)
        refined.append(best)
    refined.sort(key=lambda x: -x[0])
    modes = _distinct(P, refined, min_separation, n_modes)
    score, T, t = modes[0]
    runner = modes[1][0] if len(modes) > 1 else -math.inf
    mean_fit = score / float(w.sum())
    ambiguous = (score - runner < min_log_ratio) or (mean_fit < min_mean_fit)
    return Anchoring(T, t, score, runner, bool(ambiguous), [(m[1], m[2], m[0]) for m in modes], mean_fit)
