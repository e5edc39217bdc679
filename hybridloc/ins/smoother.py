"""Rauch-Tung-Striebel smoothing of a closed-loop error-state filter, one short interval at a time.

A foot INS is corrected only at stance. During a swing its velocity error grows unseen, and the
ZUPT at the next stance corrects the present (the velocity, and the position through their
correlation) but leaves the positions of the swing where the forward filter put them. The RTS
smoother carries that correction back over the swing (Colomar, Nilsson & Handel 2012, "Smoothing
for ZUPT-aided INSs"): with the filter's transitions Phi_k, its posterior covariances P_k|k and
its predictions P_k+1|k,

    C_k = P_k|k Phi_k+1^T P_k+1|k^-1
    e_k = C_k (e_k+1 + dx_k+1)

where e_k is the smoothed error state at sample k relative to the filter's posterior there and
dx_k+1 the correction the filter injected at k+1 (closed loop: the predicted state at k+1 is the
posterior minus dx_k+1). The interval ends at the last sample of a stance, where e = 0: after a
stance of ZUPTs the velocity is pinned, and what later data could still teach about earlier
positions (heading, position) is unobservable anyway, so interval-wise smoothing loses next to
nothing against smoothing the whole recording, with memory bounded by one stride.
"""

from __future__ import annotations

import numpy as np


class IntervalRts:
    """Buffers a filter's transitions and smooths them back when an interval is closed.

    ``add(i, Phi, P_post_prev, P_pred, dx)`` records the transition into sample ``i``: Phi, the
    posterior covariance before it, the predicted covariance after it, and the correction injected
    at ``i`` (zeros when none). ``flush()`` returns ``(indices, e)``: the smoothed error states of
    the samples before each recorded transition (the interval's start sample, then each recorded
    sample but the last, whose error is zero), and starts the next interval at the last sample.
    ``restart(i)`` drops the buffer without smoothing across (a re-initialised filter).
    """

    def __init__(self, start: int = 0, dim: int = 15):
        self._start = start
        self.dim = dim
        self._idx: list[int] = []
        self._Phi: list[np.ndarray] = []
        self._Pf: list[np.ndarray] = []
        self._Pp: list[np.ndarray] = []
        self._dx: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._idx)

    def add(self, i: int, Phi: np.ndarray, P_post_prev: np.ndarray, P_pred: np.ndarray, dx: np.ndarray) -> None:
        self._idx.append(i)
        self._Phi.append(Phi)
        self._Pf.append(P_post_prev)
        self._Pp.append(P_pred)
        self._dx.append(dx)

    def restart(self, start: int) -> None:
        self._start = start
        self._idx, self._Phi, self._Pf, self._Pp, self._dx = [], [], [], [], []

    def flush(self) -> tuple[np.ndarray, np.ndarray]:
        m = len(self._idx)
        if m == 0:
            return np.zeros(0, int), np.zeros((0, self.dim))
        Phi, Pf, Pp = np.array(self._Phi), np.array(self._Pf), np.array(self._Pp)
        try:
            # C_j^T = P_pred^-1 Phi P_post (P_pred symmetric): one batched solve for the interval
            C = np.linalg.solve(Pp, Phi @ Pf).transpose(0, 2, 1)
        except np.linalg.LinAlgError:
            self.restart(self._idx[-1])
            return np.zeros(0, int), np.zeros((0, self.dim))
        e = np.zeros((m, self.dim))  # e[j]: smoothed error at the sample before transition j
        nxt = np.zeros(self.dim)  # the error at the interval's last sample: zero
        for j in range(m - 1, -1, -1):
            nxt = C[j] @ (nxt + self._dx[j])
            e[j] = nxt
        idx = np.array([self._start] + self._idx[:-1])
        self.restart(self._idx[-1])
        return idx, e
