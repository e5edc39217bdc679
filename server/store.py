"""Persisting batches: one transaction per group of batches, idempotent by (device, seq), go-back-N.

:meth:`Store.persist` takes decoded batches in arrival order and returns, per device, the highest
sequence number now persisted (what the server acknowledges). A batch is written only if it is the
next one of its device; duplicates and gaps are counted as rejections (reasons ``duplicate`` and
``out-of-order``) and change nothing. Validation failures before this point are passed in and stored
in the same transaction.
"""

from __future__ import annotations

from collections import Counter

from sqlalchemy import insert, select
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session

from hybridloc.wire.protocol import Batch

from . import db as m
from .migrate import upgrade


class Store:
    def __init__(self, url: str, migrate: bool = True):
        self.engine: Engine = m.make_engine(url)
        if migrate:
            upgrade(self.engine)

    def close(self) -> None:
        self.engine.dispose()

    def persist(self, batches: list[Batch], invalid: Counter | None = None) -> tuple[dict[str, int], Counter, int]:
        """(highest persisted seq per device, rejections by (device, reason), batches written).

        ``invalid`` counts messages already refused by validation; they are stored in the same
        transaction (and included in the returned rejections).
        """
        acked: dict[str, int] = {}
        rejected: Counter = Counter(invalid or {})
        written = 0
        if not batches and not rejected:
            return acked, rejected, written
        with Session(self.engine) as s, s.begin():
            devices: dict[str, m.Device] = {}
            sites: set[str] = set()
            for b in batches:
                dev = devices.get(b.device)
                if dev is None:
                    dev = s.get(m.Device, b.device)
                    if dev is None:
                        if b.site not in sites and s.get(m.Site, b.site) is None:
                            s.add(m.Site(id=b.site, name=b.site))
                            s.flush()
                        sites.add(b.site)
                        dev = m.Device(id=b.device, site_id=b.site, model=b.device_model, last_seq=0)
                        s.add(dev)
                        s.flush()
                    devices[b.device] = dev
                if b.seq <= dev.last_seq:
                    rejected[(b.device, "duplicate")] += 1
                    acked[b.device] = dev.last_seq
                    continue
                if b.seq != dev.last_seq + 1:
                    rejected[(b.device, "out-of-order")] += 1
                    acked[b.device] = dev.last_seq
                    continue
                row = m.Batch(device_id=b.device, seq=b.seq, n_steps=len(b.steps), n_scans=len(b.scans), n_marks=len(b.marks))
                s.add(row)
                s.flush()
                if b.steps:
                    s.execute(insert(m.Step), [
                        {"batch_id": row.id, "device_id": b.device, "t": st.t, "length": st.length, "heading": st.heading,
                         "sigma_length": st.sigma_length, "sigma_heading": st.sigma_heading, "heading_change": st.heading_change,
                         "floor_change": st.floor_change} for st in b.steps])
                if b.scans:
                    s.execute(insert(m.Scan), [
                        {"batch_id": row.id, "device_id": b.device, "t": sc.t, "technology": sc.technology.value,
                         "readings": {"rssi": dict(sc.rssi_dbm), **({"freq": dict(sc.frequency_hz)} if sc.frequency_hz else {}),
                                      **({"age": dict(sc.age_s)} if sc.age_s else {})}}
                        for sc in b.scans])
                if b.marks:
                    s.execute(insert(m.SurveyMark), [{"batch_id": row.id, "device_id": b.device, "t": mk.t, "x": mk.x, "y": mk.y, "floor": mk.floor} for mk in b.marks])
                dev.last_seq = b.seq
                dev.last_seen = m.utcnow()
                if b.device_model and not dev.model:
                    dev.model = b.device_model
                acked[b.device] = b.seq
                written += 1
            self._add_rejections(s, rejected)
        return acked, rejected, written

    @staticmethod
    def _add_rejections(s: Session, counts: Counter) -> None:
        for (device, reason), n in counts.items():
            row = s.execute(select(m.Rejection).where(m.Rejection.device_id == device, m.Rejection.reason == reason)).scalar_one_or_none()
            if row is None:
                s.add(m.Rejection(device_id=device, reason=reason, count=n))
            else:
                row.count += n

    def last_seq(self, device: str) -> int:
        with Session(self.engine) as s:
            dev = s.get(m.Device, device)
            return dev.last_seq if dev else 0

    def add_fix(self, device: str, fix) -> None:
        self.add_fixes([(device, fix)])

    def add_fixes(self, fixes: list) -> None:
        """Store (device, AbsoluteFix) pairs in one transaction."""
        if not fixes:
            return
        with Session(self.engine) as s, s.begin():
            s.add_all([m.Fix(device_id=d, t=f.t, x=float(f.pos_enu[0]), y=float(f.pos_enu[1]), floor=f.floor, cov=f.cov.tolist(), source=f.source.value)
                       for d, f in fixes])

    # -------------------------------------------------------------- radio maps
    def save_map(self, site: str, data: bytes, n_scans: int = 0) -> int:
        with Session(self.engine) as s, s.begin():
            if s.get(m.Site, site) is None:
                s.add(m.Site(id=site, name=site))
                s.flush()
            last = s.execute(select(m.RadioMapVersion.version).where(m.RadioMapVersion.site_id == site).order_by(m.RadioMapVersion.version.desc())).first()
            v = (last[0] if last else 0) + 1
            s.add(m.RadioMapVersion(site_id=site, version=v, n_scans=n_scans, data=data))
            return v

    def load_map(self, site: str) -> tuple[int, bytes] | None:
        with Session(self.engine) as s:
            row = s.execute(select(m.RadioMapVersion).where(m.RadioMapVersion.site_id == site).order_by(m.RadioMapVersion.version.desc())).scalars().first()
            return (row.version, row.data) if row else None

    def status(self) -> dict:
        from sqlalchemy import func

        with Session(self.engine) as s:
            return {
                "devices": s.execute(select(func.count()).select_from(m.Device)).scalar_one(),
                "batches": s.execute(select(func.count()).select_from(m.Batch)).scalar_one(),
                "steps": s.execute(select(func.count()).select_from(m.Step)).scalar_one(),
                "scans": s.execute(select(func.count()).select_from(m.Scan)).scalar_one(),
                "marks": s.execute(select(func.count()).select_from(m.SurveyMark)).scalar_one(),
                "fixes": s.execute(select(func.count()).select_from(m.Fix)).scalar_one(),
                "rejections": _rejections(s),
                "maps": {site: v for site, v in s.execute(select(m.RadioMapVersion.site_id, func.max(m.RadioMapVersion.version)).group_by(m.RadioMapVersion.site_id)).all()},
            }


def _rejections(s: Session) -> dict:
    out: Counter = Counter()
    for r in s.execute(select(m.Rejection)).scalars():
        out[r.reason] += r.count
    return dict(out)
