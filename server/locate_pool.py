"""Locating scans in worker processes: ``hybridloc serve --locate-workers N``.

The server answers each stored batch's newest WiFi scan (:meth:`.service.Server._answer`). On a site1
map an answer costs about 1.3 ms of CPU (the kNN search, the containment region, the FIX message), and
the locate thread shares one interpreter lock with the ingest thread: at 1,000 phone clients the
server ran on about one core of two (``benchmarks/bench_load.py``). With workers, the locate thread
sends each group of scans to worker processes and waits (its wait releases the lock). A worker holds
the site's locator, answers, encodes the FIX messages and returns them with the fixes to store; the
server stores the fixes and pushes the messages as before. The answers are the in-process ones: the
same locator (:func:`make_locator`) on the same map, the same conversion (:func:`answers`).

Maps reach the workers as files: each map version the server loads is written once into a temporary
folder, and a request names (site, version, path); a worker loads a version the first time it is asked
for it. A version's file is removed only when no request can still name it (at the next call: the
locate thread is the only caller, and it waits for each call's answers). Labels grown on top of a
version (:meth:`LocatePool.add_labels`) reach them the same way, as a file of every such label. A
worker that dies (killed, out of memory), fails (a map it cannot read) or takes longer than
``timeout_s``: :class:`PoolBroken` tells the server, which answers that group in-process; a dead or
stuck pool is replaced for the next group. After :meth:`LocatePool.close` every group is answered
in-process.

Workers are spawned (never forked: the server has Zenoh's threads), run one BLAS thread at a lower CPU
priority than ingest (an acknowledgement never waits on a fix), and exit when the server is gone.
"""

from __future__ import annotations

import logging
import os
import pickle
import shutil
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

from hybridloc.radio.locate import KnnLocator, ProbabilisticLocator
from hybridloc.radio.radiomap import RadioMap
from hybridloc.types import AbsoluteFix, Fix, RfScan
from hybridloc.wire import codecs as C

from .child_process import yield_to_server

log = logging.getLogger("hybridloc.server")


class KnnOne:
    """One-scan ``locate`` on top of the batch kNN locator."""

    def __init__(self, knn: KnnLocator):
        self.knn = knn

    def locate(self, scan):
        return self.knn.locate_many([scan])[0]

    def locate_many(self, scans):
        return self.knn.locate_many(scans) if scans else []


def make_locator(rmap: RadioMap, method: str):
    """The server's locator of a map: weighted kNN over the map's reference scans by default
    (calibrated 95 % regions on the Indoor Location Competition data); the cell likelihood when asked
    (``method="prob"``) or when the map has no references."""
    if method == "knn" and rmap.references:
        return KnnOne(KnnLocator(rmap.references, max_age_s=8.0))
    return ProbabilisticLocator(rmap, max_age_s=8.0)


def answers(loc, scans: list[RfScan]) -> list[Fix]:
    """The answer to each scan: a fix with its containment region and floor probabilities, or "no fix"
    with the reason and the scan's time (one locator call for all of them with kNN)."""
    results = loc.locate_many(scans) if isinstance(loc, KnnOne) else [loc.locate(sc) for sc in scans]
    return [Fix(None, reason=res.reason, t=sc.t) if res.fix is None else Fix(res.fix, res.region, res.floor_probs) for sc, res in zip(scans, results)]


class PoolBroken(RuntimeError):
    """A worker process died while it answered (the group is to be answered in-process)."""


# ------------------------------------------------------------------------------------------ the workers
_LOCATORS: dict[str, tuple[tuple[int, str], object]] = {}  # site -> ((map version, labels file), locator), in a worker
_BASES: dict[str, tuple[int, object]] = {}  # site -> (map version, the version's own locator), in a worker
_METHOD = "knn"


def _init(parent_pid: int, method: str) -> None:
    global _METHOD
    _METHOD = method
    yield_to_server(parent_pid, 5, "hybridloc-locate-watch")


def _answer_in_worker(site: str, version: int, path: str, scans: list[RfScan], labels: str = "") -> list[tuple[bytes, AbsoluteFix | None]]:
    held = _LOCATORS.get(site)
    if held is None or held[0] != (version, labels):
        base = _BASES.get(site)
        if base is None or base[0] != version:
            base = (version, make_locator(RadioMap.load(path), _METHOD))
            _BASES[site] = base
        loc = base[1]
        if labels and isinstance(loc, KnnOne):  # the labels grown on top of the version (Server.add_labels)
            with open(labels, "rb") as f:
                loc = KnnOne(loc.knn.extended(pickle.load(f)))
        held = ((version, labels), loc)
        _LOCATORS[site] = held
    return [(C.FIX.encode(a), a.fix) for a in answers(held[1], scans)]


# ------------------------------------------------------------------------------------------ the pool
class LocatePool:
    """``workers`` processes answering groups of scans (module docstring)."""

    def __init__(self, workers: int, method: str = "knn", timeout_s: float = 60.0):
        if workers < 1:
            raise ValueError(f"a locate pool needs at least one worker, got {workers}")
        self.workers, self.method, self.timeout_s = workers, method, timeout_s
        self._dir = Path(tempfile.mkdtemp(prefix="hybridloc-locate-"))
        self._maps: dict[str, tuple[int, str, str]] = {}  # site -> (version, file, labels file or "")
        self._labels_made = 0
        self._stale: list[str] = []  # files of replaced versions, removed at the next call
        self._lock = threading.Lock()
        self._ex: ProcessPoolExecutor | None = None
        self._closed = False
        self.restarts = 0

    def _executor(self) -> ProcessPoolExecutor:
        if self._closed:
            raise RuntimeError("the locate pool is closed")
        if self._ex is None:
            import multiprocessing as mp

            self._ex = ProcessPoolExecutor(self.workers, mp_context=mp.get_context("spawn"), initializer=_init, initargs=(os.getpid(), self.method))
        return self._ex

    def add_map(self, site: str, version: int, blob: bytes) -> None:
        """Make map ``version`` of ``site`` the one its scans are answered with (written once to a file
        the workers read; the file of the version before is removed)."""
        path = self._dir / f"{site}-{version}.npz"
        if not path.exists():
            # written whole under another name, then renamed: a worker never reads half a map
            tmp = path.with_suffix(".part")
            tmp.write_bytes(blob)
            os.replace(tmp, path)
        with self._lock:
            old = self._maps.get(site)
            self._maps[site] = (version, str(path), "")
            if old is not None:
                if old[1] != str(path):
                    self._stale.append(old[1])  # a request made before this one may still name it
                if old[2]:
                    self._stale.append(old[2])

    def add_labels(self, site: str, version: int, labels: list) -> None:
        """Answer ``site``'s scans from map ``version`` plus ``labels`` (every label grown on top of it so
        far: :meth:`.service.Server.add_labels`), written to a file the workers read; ignored when the
        site's current map is another version."""
        with self._lock:
            held = self._maps.get(site)
            if held is None or held[0] != version:
                return
            self._labels_made += 1
            path = self._dir / f"{site}-{version}-labels-{self._labels_made}.pkl"
        tmp = path.with_suffix(".part")
        tmp.write_bytes(pickle.dumps(list(labels), protocol=pickle.HIGHEST_PROTOCOL))
        os.replace(tmp, path)
        with self._lock:
            held = self._maps.get(site)
            if held is None or held[0] != version:  # a new version came meanwhile
                self._stale.append(str(path))
                return
            self._maps[site] = (version, held[1], str(path))
            if held[2]:
                self._stale.append(held[2])

    def answer(self, site: str, scans: list[RfScan]) -> list[tuple[bytes, AbsoluteFix | None]] | None:
        """(FIX message, fix or None) of each scan, in order; None when the site has no map here.
        The scans are split over the workers. PoolBroken when a worker died meanwhile (a new pool is
        made for the next call)."""
        with self._lock:
            if self._closed:
                return None
            held = self._maps.get(site)
            # every earlier call has returned (the locate thread waits for each): no request names these
            stale, self._stale = self._stale, []
        for f in stale:
            Path(f).unlink(missing_ok=True)
        if held is None:
            return None
        if not scans:
            return []
        version, path, labels = held
        n = min(self.workers, len(scans))
        size = -(-len(scans) // n)
        try:
            ex = self._executor()
            futs = [ex.submit(_answer_in_worker, site, version, path, scans[i : i + size], labels) for i in range(0, len(scans), size)]
            deadline = time.monotonic() + self.timeout_s
            return [x for f in futs for x in f.result(timeout=max(0.0, deadline - time.monotonic()))]
        except (BrokenProcessPool, TimeoutError) as exc:
            # dead, or stuck: this pool is replaced (its processes ended) for the next group
            self._restart()
            raise PoolBroken(f"{type(exc).__name__}: {exc}" if str(exc) else "a locate worker process died or took too long") from exc
        except Exception as exc:
            # a worker's own failure (a map it cannot read, memory): the pool still works
            raise PoolBroken(f"{type(exc).__name__}: {exc}") from exc

    def _restart(self) -> None:
        self.restarts += 1
        ex, self._ex = self._ex, None
        if ex is not None:
            procs = list(getattr(ex, "_processes", {}).values())
            ex.shutdown(wait=False, cancel_futures=True)
            for p in procs:  # a stuck worker would otherwise live on
                if p.is_alive():
                    p.kill()

    def close(self) -> None:
        with self._lock:
            self._closed = True
        ex, self._ex = self._ex, None
        if ex is not None:
            procs = list(getattr(ex, "_processes", {}).values())
            ex.shutdown(wait=False, cancel_futures=True)
            for p in procs:  # idle workers exit at once; a stuck one is ended
                p.join(5.0)
                if p.is_alive():
                    p.kill()
                    p.join(5.0)
        shutil.rmtree(self._dir, ignore_errors=True)
