"""``hybridloc serve``: one process, one Zenoh session in router mode, a worker thread for the database.

Threads:

* Zenoh's own threads deliver samples into a bounded FIFO channel (``FifoChannel``): when the worker
  falls behind, the channel fills and Zenoh's BLOCK congestion control pushes back on the clients.
* the ingest worker drains the channel in groups (up to ``max_group`` samples or ``max_wait`` s),
  validates every message, persists the group in one transaction, publishes the acknowledgements and
  hands the newest WiFi scan of each stored batch to the locate worker;
  with ``ingest_workers`` (``serve --ingest-workers N``) it only hands each device's messages to its
  worker process (:mod:`.ingest_pool`), which validates and persists them with the same code
  (:mod:`.ingest`); the pool's reader threads publish the acknowledgements and hand the scans on;
* with SQLite, a thread checkpoints the WAL beside the writers (:class:`.db.WalCheckpointer`);
* the locate worker answers those scans (a fix, or "no fix" with the reason), stores the fixes and
  pushes them to their devices. It runs beside ingest, so locating never delays an acknowledgement;
  when it falls behind, it sheds load: of a device's scans waiting together only the newest is
  located, the older ones are answered "no fix, superseded" (a fix for where the walker was seconds
  ago is worth less than the next one, and a client always hears back). With ``locate_workers``
  (``serve --locate-workers N``) the answers are computed in worker processes (:mod:`.locate_pool`),
  off this process's interpreter lock, which ingest then has to itself; the answers are the same;
* queryable callbacks (locate, map, status) answer from memory and are short;
* one crowd-SLAM worker per SLAM site (:mod:`.slam_worker`): a thread that only waits on its spawned
  child process, where the solves run, and publishes corrected tracks, map versions and progress. It
  never touches the ingest path: a slow, failing or crashing solve delays no acknowledgement.

Nothing is acknowledged before it is committed, so a crash (even SIGKILL) loses only unacknowledged
batches, which clients resend.
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass

import zenoh

from hybridloc.radio.locate import ProbabilisticLocator
from hybridloc.radio.radiomap import RadioMap
from hybridloc.radio.survey import LabelledScan
from hybridloc.types import Fix, RfScan
from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.messages import Ack, MapInfo, Status
from hybridloc.wire.zconfig import Security, server_config, zenoh_reason

from . import db as m
from .ingest import IngestResult, Stopping, ingest_group, with_database
from .ingest_pool import IngestPool, resolve_ingest_workers
from .locate_pool import KnnOne, LocatePool, PoolBroken, answers, make_locator
from .slam_store import CORRECTED
from .slam_worker import SlamOptions, SlamWorker
from .store import Store

log = logging.getLogger("hybridloc.server")


@dataclass
class _Grown:
    """A site's map version as served with ``SlamOptions.grow_map``: the version's own kNN locator, the
    labels grown on top of it (in the order they came) and the walks (label sources) it holds."""

    base: KnnOne
    labels: list[LabelledScan]
    held: set[str]


class Server:
    def __init__(
        self,
        endpoint: str,
        db_url: str,
        security: Security | None = None,
        max_group: int = 500,
        max_wait: float = 0.02,
        method: str = "knn",
        slam_sites: list[str] | None = None,
        slam_options: SlamOptions | None = None,
        sites: list[str] | None = None,
        connect: list[str] | None = None,
        locate_workers: int = 0,
        ingest_workers: int | str = 0,
    ):
        #: the sites this process serves (ingest, locate, maps): None or empty = every site. Processes
        #: serving different sites share one router mesh (``connect``: other routers) and one database.
        self.sites = [P.check_id(x, "site") for x in dict.fromkeys(sites or ())]
        self.connect = list(connect or ())
        self.endpoint = endpoint
        self.db_url = db_url
        # SQLite: the WAL checkpointed by a thread beside the writers (started with the server), the
        # writers' own autocheckpoint only its safety net (db.WalCheckpointer)
        self._wal_path = m.sqlite_path(db_url)
        self.store = Store(db_url, wal_autocheckpoint=m.INGEST_WAL_AUTOCHECKPOINT if self._wal_path else None)
        self._checkpointer: m.WalCheckpointer | None = None
        self.slam_sites = list(dict.fromkeys(slam_sites or ()))
        self.slam_options = slam_options
        self.slam_workers: dict[str, SlamWorker] = {}
        self.security = security
        self.max_group = max_group
        self.max_wait = max_wait
        self.session: zenoh.Session | None = None
        self.counts: Counter = Counter()  # message counts by kind and rejection reason
        self.online: set[str] = set()
        self.locators: dict[str, tuple[int, ProbabilisticLocator, bytes]] = {}
        #: per site: the served version's own locator (kNN) and the labels of the walks the SLAM worker
        #: added since that version (``SlamOptions.grow_map``: :meth:`add_labels`), which the served
        #: locator holds on top of it
        self._grown: dict[str, _Grown] = {}
        #: per site: every walk (label source) whose labels were ever served that way
        self.grown_walks: dict[str, set[str]] = {}
        self._entities: list = []
        self._worker: threading.Thread | None = None
        self._locate_worker: threading.Thread | None = None
        self._asked: deque = deque()  # (batch, its newest WiFi scan) stored, waiting for an answer
        self._asked_cv = threading.Condition()
        self._ingest_done = threading.Event()  # set when the ingest worker has returned: nothing more to answer
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        self.worker_error: BaseException | None = None
        if method not in ("knn", "prob"):
            raise ValueError("method must be knn or prob")
        self.method = method
        if locate_workers < 0:
            raise ValueError(f"locate_workers must be >= 0, got {locate_workers}")
        #: worker processes answering the stored scans (:mod:`.locate_pool`); None: the locate thread itself
        self._pool: LocatePool | None = LocatePool(locate_workers, method) if locate_workers else None
        #: worker processes ingesting the batches (:mod:`.ingest_pool`, made at start); 0: the ingest thread
        #: itself; "auto": :func:`.ingest_pool.resolve_ingest_workers` (2 on two cores or more)
        self.ingest_workers = resolve_ingest_workers(ingest_workers, db_url)
        self._ingest_pool: IngestPool | None = None
        self._counts_lock = threading.Lock()

    # ------------------------------------------------------------ lifecycle
    def start(self) -> Server:
        """Open the session, declare the keys and start the threads (and processes); what was started
        is stopped again when a step fails (a Zenoh endpoint in use, a worker that cannot start)."""
        try:
            return self._start()
        except BaseException:
            if self._worker is None and self._ingest_pool is not None:  # made, but no ingest thread to close it
                self._ingest_pool.close(timeout_s=5.0)
                self._ingest_pool = None
            self.stop()
            raise

    def _start(self) -> Server:
        if self._wal_path is not None:
            self._checkpointer = m.WalCheckpointer(self._wal_path).start()
        try:
            self.session = zenoh.open(server_config(self.endpoint, self.security, self.connect))
        except zenoh.ZError as exc:  # an endpoint in use or not ours to listen on: the user's to mend, in one line
            why = zenoh_reason(exc, 400)
            hint = " (another server listening there?)" if "in use" in why else ""
            raise OSError(f"cannot open the server's Zenoh session on {self.endpoint}{hint}: {why}") from exc
        s = self.session
        # every site's keys, or only the served sites' (a key expression per site: hl/v1/<site>/...)
        batch_keys = [P.SUB_BATCHES] if not self.sites else [P.sub_batches(x) for x in self.sites]
        locate_keys = [P.SUB_LOCATE] if not self.sites else [P.sub_locate(x) for x in self.sites]
        map_keys = [P.SUB_MAPS] if not self.sites else [P.key_map(x) for x in self.sites]
        self._subs = [s.declare_subscriber(k, zenoh.handlers.FifoChannel(20000)) for k in batch_keys]
        self._next_sub = 0
        self._entities += [
            *self._subs,
            *(s.declare_queryable(k, self._on_locate) for k in locate_keys),
            *(s.declare_queryable(k, self._on_map) for k in map_keys),
            s.declare_queryable(P.KEY_STATUS, self._on_status),
            s.liveliness().declare_subscriber(P.SUB_ALIVE, self._on_alive, history=True),
        ]
        if self.ingest_workers:
            self._ingest_pool = IngestPool(self.ingest_workers, self.db_url, self._deliver, self._count_all, self.max_group)
        self._worker = threading.Thread(target=self._run, name="hybridloc-ingest", daemon=True)
        self._worker.start()
        self._locate_worker = threading.Thread(target=self._run_locate, name="hybridloc-locate", daemon=True)
        self._locate_worker.start()
        for site in self.slam_sites:
            P.check_id(site, "site")
            self.slam_workers[site] = SlamWorker(
                self.db_url,
                site,
                self._publish,
                self.slam_options,
                on_map=self.load_map,
                online=self._online_now,
                on_added=self.grow_walk,
            ).start()
        return self

    def _online_now(self) -> set[str]:
        """A copy of the devices online (the liveliness callback changes the set from its own thread)."""
        while True:
            try:
                return set(self.online)
            except RuntimeError:  # changed size during the copy: copy again
                continue

    def _publish(self, key: str, payload: bytes, encoding: str) -> None:
        s = self.session
        if s is not None:
            s.put(key, payload, encoding=encoding)

    def request_batch(self, site: str) -> None:
        """Re-solve the site's floors in batch now (on demand); KeyError for a site without a SLAM worker."""
        self.slam_workers[site].request_batch()

    def stop(self) -> None:
        for w in self.slam_workers.values():
            w.stop()
        self.slam_workers.clear()
        self._stopping.set()
        if self._worker is not None:
            self._worker.join(timeout=10)
        if self._locate_worker is not None:  # after ingest: it answers what ingest stored before it stopped
            with self._asked_cv:
                self._asked_cv.notify()
            self._locate_worker.join(timeout=10)
        for e in self._entities:
            try:
                e.undeclare()
            except Exception:  # noqa: BLE001 - already gone at shutdown
                pass
        self._entities.clear()
        if self._pool is not None:
            self._pool.close()
        if self._checkpointer is not None:
            self._checkpointer.stop()
            self._checkpointer = None
        if self.session is not None:
            self.session.close()
            self.session = None
        self.store.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # ------------------------------------------------------------ maps
    def load_map(self, site: str, data: bytes | None = None) -> int | None:
        """Use the newest stored radio map of ``site`` (or store ``data`` as a new version first)."""
        import io

        if data is not None:
            self.store.save_map(site, data)
        got = self.store.load_map(site)
        if got is None:
            return None
        version, blob = got
        rmap = RadioMap.load(io.BytesIO(blob))
        loc = make_locator(rmap, self.method)
        with self._lock:
            cur = self.locators.get(site)
            if cur is not None and cur[0] > version:
                return cur[0]  # another thread installed a newer version meanwhile
            if self._pool is not None:
                self._pool.add_map(site, version, blob)
            held: set[str] = set()
            if isinstance(loc, KnnOne):
                held = {r.source for r in rmap.references}
                self._grown[site] = _Grown(loc, [], held)
            else:
                self._grown.pop(site, None)
            self.locators[site] = (version, loc, blob)
        if site in self._grow_sites and isinstance(loc, KnnOne):
            # the walks added since the version's labels were taken keep theirs until a version holds them
            self.add_labels(site, self._placed_walk_labels(site, held))
        return version

    @property
    def _grow_sites(self) -> set[str]:
        """The sites whose served map grows at every added walk (``SlamOptions.grow_map``)."""
        o = self.slam_options
        return set(self.slam_sites) if o is not None and o.grow_map else set()

    def grow_walk(self, site: str, walk_id: int) -> int:
        """Serve walk ``walk_id``, just added by the site's SLAM worker, on top of the map version
        (``SlamOptions.grow_map``): its labels by :meth:`_placed_walk_labels`' rule. Returns the walks
        taken (0 or 1)."""
        g = self._grown.get(site)
        return self.add_labels(site, self._placed_walk_labels(site, g.held, [walk_id])) if g is not None else 0

    def _placed_walk_labels(self, site: str, held: set[str], walk_ids: list[int] | None = None) -> list[LabelledScan]:
        """The labels a grown map serves on top of a version that holds the walks ``held``: those of every
        crowd walk (or of ``walk_ids``) whose stored track is corrected and absolute and that the version
        does not hold, each scan at its track's position (:func:`~hybridloc.slam.online.labels_from_tracks`,
        as a batch's crowd map labels it) - read from the database, so a restarted server serves them too,
        and a walk a batch made relative or put aside since it was added has none. A survey walk (with
        marks) has none either: its marks label it in the next ``map rebuild`` or batch map, and a survey
        map names its labels by device, so they could not be told from the map's own."""
        from hybridloc.slam.online import labels_from_tracks  # the SLAM library only where a map grows

        states = self.store.slam.walk_states(site)
        want = states if walk_ids is None else {w: states[w] for w in walk_ids if w in states}
        ids = [w for w, st in want.items() if st.status == CORRECTED and st.anchored != "relative" and str(w) not in held]
        if not ids:
            return []
        marked = {w.walk_id for w in self.store.walks(site) if w.n_marks}
        ids = [w for w in ids if w not in marked]
        tracks = self.store.slam.tracks(site, walk_ids=ids)
        return labels_from_tracks([self.store.read_walk(w) for w in ids if w in tracks], tracks)

    def add_labels(self, site: str, labels: list[LabelledScan]) -> int:
        """Serve ``site``'s scans from its map version plus ``labels`` (walks the SLAM worker added: their
        scans at their corrected positions, ``SlamOptions.grow_map``), which replace any earlier
        labels of the same walks (``source``). Held in memory only, on top of the version: a new
        version takes over the labels of the walks it holds and keeps the others' while their walks
        stay placed (corrected, absolute); the map key still serves the stored version. kNN only (the
        default ``--method``): the cell likelihood is built from the whole map. Labels of a walk the
        version holds, or of another technology than the map's, are not taken. Returns the number of
        walks whose labels were taken (0: none; no map, or a map without kNN references)."""
        with self._lock:
            g = self._grown.get(site)
            cur = self.locators.get(site)
            if g is None or cur is None:
                return 0
            tech = g.base.knn.refs[0].scan.technology
            new = [ls for ls in labels if ls.scan.technology == tech and ls.source not in g.held]
            if not new:
                return 0
            mine = {ls.source for ls in new}
            again = any(ls.source in mine for ls in g.labels)
            grown = [ls for ls in g.labels if ls.source not in mine] + new
            # the served locator is the base extended by g.labels: extend it by the new walk alone, or
            # the base by every label when a walk's labels are replaced
            knn = g.base.knn.extended(grown) if again else cur[1].knn.extended(new)
            self._grown[site] = _Grown(g.base, grown, g.held)
            self.locators[site] = (cur[0], KnnOne(knn), cur[2])
            if self._pool is not None:
                self._pool.add_labels(site, cur[0], grown)
            self.counts["map-walks-grown"] += len(mine - self.grown_walks.setdefault(site, set()))
            self.grown_walks[site] |= mine
            return len(mine)

    def answer(self, site: str, scan: RfScan) -> Fix:
        """The answer to one scan, pushed after a batch and replied to a locate query alike: a fix with
        its containment region and floor probabilities, or "no fix" with the reason (no map for the
        site, no known transmitter ...) and the scan's time."""
        loc = self.locators.get(site)
        if loc is None:
            return Fix(None, reason=f"no radio map for site {site!r}", t=scan.t)
        res = loc[1].locate(scan)
        if res.fix is None:
            return Fix(None, reason=res.reason, t=scan.t)
        return Fix(res.fix, res.region, res.floor_probs)

    def answer_many(self, site: str, scans: list[RfScan]) -> list[Fix]:
        """:meth:`answer` for each of ``scans`` (one locator call for all of them)."""
        loc = self.locators.get(site)
        if loc is None:
            return [Fix(None, reason=f"no radio map for site {site!r}", t=sc.t) for sc in scans]
        return answers(loc[1], scans)

    def _answer_site(self, site: str, scans: list[RfScan]) -> list[tuple[bytes, object]]:
        """(FIX message, fix or None) of each scan: from the locate workers when the server has them,
        else (and when a worker died meanwhile) from this process; the same answers either way."""
        if self._pool is not None:
            try:
                got = self._pool.answer(site, scans)
            except PoolBroken as exc:
                self.counts["locate-pool-failures"] += 1
                log.error("the locate workers failed (%s): %d scans answered here", exc, len(scans))
            else:
                if got is not None:
                    return got
        return [(C.FIX.encode(a), a.fix) for a in self.answer_many(site, scans)]

    # ------------------------------------------------------------ ingest
    def _run(self) -> None:
        try:
            self._ingest_loop()
        finally:
            if self._ingest_pool is not None:  # its workers ingest what they were sent, and it is answered
                try:
                    self._ingest_pool.close(timeout_s=8.0)
                except Exception:  # noqa: BLE001 - shutting down: what is not acknowledged is resent
                    log.exception("closing the ingest workers failed")
            self._ingest_done.set()
            with self._asked_cv:
                self._asked_cv.notify()

    def _ingest_loop(self) -> None:
        try:
            while True:
                # poll (a blocking recv() is not woken when the subscriber is undeclared, which made
                # every stop wait for the join timeout); messages already queued are still ingested
                try:
                    first = self._try_recv()
                except zenoh.ZError:
                    return  # undeclared or closed: shutting down
                if first is None:
                    if self._stopping.is_set():
                        return
                    time.sleep(0.002)
                    continue
                group = [first]
                deadline = time.monotonic() + self.max_wait
                while len(group) < self.max_group:
                    nxt = self._try_recv()
                    if nxt is None:
                        if time.monotonic() >= deadline:
                            break
                        time.sleep(0.001)
                        continue
                    group.append(nxt)
                try:
                    self._ingest(group)
                except Stopping:
                    return  # stopped while the database was away (a group not yet stored is not acknowledged)
                except Exception:  # noqa: BLE001 - a bad group must not end ingest: the batches it did not
                    # store are not acknowledged, so their devices resend them; the next group goes on
                    self.counts["ingest-errors"] += 1
                    log.exception("ingest of a group of %d messages failed; what it did not store stays unacknowledged", len(group))
        except BaseException as exc:  # noqa: BLE001 - recorded, never silently lost
            self.worker_error = exc
            log.exception("ingest worker stopped")

    def _try_recv(self):
        """The next batch sample of the served sites' subscriptions, taken in turn so that a busy site
        does not starve the others (None: none waiting)."""
        n = len(self._subs)
        for k in range(n):
            i = (self._next_sub + k) % n
            smp = self._subs[i].try_recv()
            if smp is not None:
                self._next_sub = (i + 1) % n
                return smp
        return None

    def _with_database(self, fn, *args, **kwargs):
        """``fn(*args, **kwargs)``, retried while the database is unreachable (:func:`.ingest.with_database`);
        raises Stopping when the server stops."""
        return with_database(lambda: fn(*args, **kwargs), self.counts, self._stopping, self._counts_lock)

    def _count_all(self, counts: Counter) -> None:
        with self._counts_lock:
            self.counts.update(counts)

    def _ingest(self, samples) -> None:
        if self._ingest_pool is not None:
            self._ingest_pool.submit([(str(smp.key_expr), smp.payload.to_bytes()) for smp in samples], _device_of_key, self._stopping)
            return
        got = ingest_group(self.store, [(str(smp.key_expr), smp.payload.to_bytes()) for smp in samples], self._with_database, self.counts)
        self._deliver(got)

    def _deliver(self, got: IngestResult) -> None:
        """Publish a group's acknowledgements, then hand its stored batches' newest WiFi scans to the
        locate worker."""
        session = self.session
        if session is None:
            return  # stopped: what was stored and not acknowledged is resent and acknowledged as a duplicate
        for site, device, seq in got.acks:
            session.put(
                P.key_ack(site, device),
                C.ACK.encode(Ack(device, seq)),
                encoding=C.ACK.encoding,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        if got.asked:
            with self._asked_cv:
                self._asked.extend(got.asked)
                self._asked_cv.notify()

    # ------------------------------------------------------------ answers
    def _run_locate(self) -> None:
        """The locate worker: takes every scan waiting, answers them, until ingest has stopped and none is left."""
        try:
            while True:
                with self._asked_cv:
                    while not self._asked and not self._ingest_done.is_set():
                        self._asked_cv.wait(0.5)
                    if not self._asked:
                        return
                    todo = list(self._asked)
                    self._asked.clear()
                try:
                    self._answer(todo)
                except Stopping:
                    return
                except Exception:  # noqa: BLE001 - a failed answer must not end the answers (the data is stored)
                    self.counts["locate-errors"] += 1
                    log.exception("answering %d scans failed; their devices hear no answer for them", len(todo))
        except BaseException as exc:  # noqa: BLE001 - recorded, never silently lost
            self.worker_error = exc
            log.exception("locate worker stopped")

    def _answer(self, asked: list[tuple]) -> None:
        """Answer ``asked`` (batch, scan) pairs in order: of a device's, only the newest is located (load
        shedding, module docstring); the fixes stored in one transaction before any is pushed."""
        newest: dict[tuple[str, str], int] = {}
        for i, (b, sc) in enumerate(asked):
            k = (b.site, b.device)
            j = newest.get(k)
            if j is None or sc.t >= asked[j][1].t:
                newest[k] = i
        keep = set(newest.values())
        out: list = [None] * len(asked)  # (FIX message, fix or None) per scan
        for i, (_, sc) in enumerate(asked):
            if i not in keep:
                shed = Fix(None, reason="superseded: a newer scan of this device was waiting to be located", t=sc.t)
                out[i] = (C.FIX.encode(shed), None)
                self.counts["fixes-shed"] += 1
        for site in dict.fromkeys(asked[i][0].site for i in keep):
            mine = [i for i in sorted(keep) if asked[i][0].site == site]
            # the site's scans located in one call: one fingerprint matrix, one neighbour search (the
            # same answers as one call per scan)
            for i, a in zip(mine, self._answer_site(site, [asked[i][1] for i in mine])):
                self.counts["fixes-pushed" if a[1] is not None else "no-fix-pushed"] += 1
                out[i] = a
        self._with_database(self.store.add_fixes, [(b.device, a[1]) for (b, _), a in zip(asked, out) if a[1] is not None])
        # blocked on congestion as the acks are (a dropped fix is an answer the client never hears: under
        # bench_load's reconnect bursts and on PostgreSQL at 1,000 clients, a few per cent were dropped)
        block = zenoh.CongestionControl.BLOCK
        for (b, _), a in zip(asked, out):
            self.session.put(P.key_fix(b.site, b.device), a[0], encoding=C.FIX.encoding, congestion_control=block)

    # ------------------------------------------------------------ queryables
    def _on_locate(self, q: zenoh.Query) -> None:
        try:
            site, device, _ = P.parse_key(str(q.key_expr))
            request = C.LOCATE.decode(q.payload.to_bytes() if q.payload else b"")
            a = self.answer(site, request.scan)
            self.counts["locate-queries"] += 1
            q.reply(str(q.key_expr), C.FIX.encode(a), encoding=C.FIX.encoding)
        except Exception as exc:  # noqa: BLE001 - a bad query gets an error reply, never a crash
            # every refusal counts as bad-locate (the decoder's own reason is in the reply)
            self.counts["rejected:bad-locate"] += 1
            q.reply_err(f"bad locate request: {exc}".encode())

    def _on_map(self, q: zenoh.Query) -> None:
        try:
            site = str(q.key_expr).split("/")[2]
            loc = self.locators.get(site)
            if loc is None:
                q.reply_err(f"no radio map for site {site!r}".encode())
                return
            q.reply(str(q.key_expr), loc[2], encoding="application/octet-stream", attachment=C.MAP_INFO.encode(MapInfo(site, loc[0])))
        except Exception as exc:  # noqa: BLE001
            q.reply_err(str(exc).encode())

    def _on_status(self, q: zenoh.Query) -> None:
        try:
            slam = {site: dict(self.store.slam.summary(site), worker=w.status()) for site, w in list(self.slam_workers.items())}
            st = Status(
                sorted(self._online_now()),
                dict(self.counts),
                self.store.status(),
                {k: v[0] for k, v in self.locators.items()},
                slam,
                self.sites,
                self.store.rejections_by_device(),
            )
            q.reply(P.KEY_STATUS, C.STATUS.encode(st), encoding=C.STATUS.encoding)
        except Exception as exc:  # noqa: BLE001
            q.reply_err(str(exc).encode())

    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            _, device, _ = P.parse_key(str(sample.key_expr))
        except ValueError:
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self.online.add(device)
        else:
            self.online.discard(device)


def _device_of_key(key: str) -> str:
    """The device a batch key names ("?" for a key that names none: refused as bad-key by whichever worker)."""
    try:
        return P.parse_key(key)[1]
    except ValueError:
        return "?"


def serve_forever(server: Server, beside=None) -> None:
    """Run ``server`` until SIGTERM or SIGINT. ``beside(server)``, when given, starts something that
    lives with it once it listens (the dashboard of ``serve --http``) and returns an object whose
    ``stop()`` ends it before the server stops."""
    import signal

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    with server:
        # what the process loaded to start (modules, the radio maps) is left out of the collector's scans:
        # ingest allocates thousands of objects a batch, and each full collection walked all of it again
        gc.freeze()
        n = server.ingest_workers
        workers = f", ingest in {n} worker process{'es' if n > 1 else ''}" if n else ""
        print(f"hybridloc server listening on {server.endpoint} (router mode{workers})", flush=True)
        extra = beside(server) if beside is not None else None
        try:
            while not stop.is_set():
                stop.wait(0.5)
                if server.worker_error is not None:
                    raise RuntimeError(f"ingest worker failed: {server.worker_error}")
        finally:
            if extra is not None:
                extra.stop()
