"""Small helpers the server and wire tests share."""

from __future__ import annotations

import os
import signal
import time


def wait_until(cond, timeout: float = 10.0, poll: float = 0.02) -> bool:
    """Poll ``cond()`` until it is true (True) or ``timeout`` seconds pass (False)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(poll)
    return False


def stored_stream(db: str, device: str | None = None) -> tuple[list[int], int]:
    """(batch sequence numbers stored, in order; steps stored) of ``device`` (None: every device's
    sequence numbers) in the database at ``db`` (a SQLite path or any URL); the steps are counted over
    every device."""
    from sqlalchemy import func, select
    from sqlalchemy.orm import Session

    from hybridloc.server import db as m

    eng = m.make_engine(str(db))
    q = select(m.Batch.seq).order_by(m.Batch.seq)
    if device is not None:
        q = q.where(m.Batch.device_id == device)
    with Session(eng) as ses:
        seqs = [r[0] for r in ses.execute(q)]
        n_steps = ses.execute(select(func.count()).select_from(m.Step)).scalar_one()
    eng.dispose()
    return seqs, int(n_steps)


def interrupt_group(proc, timeout: float = 60.0) -> str:
    """Ctrl-C as a terminal sends it: SIGINT to the process group of ``proc`` (started with
    ``start_new_session=True``); the rest of its output once it has ended."""
    os.killpg(proc.pid, signal.SIGINT)
    out, _ = proc.communicate(timeout=timeout)
    return out


def kill_group(proc) -> None:
    """SIGKILL the process group of ``proc`` if it still runs (a test's cleanup)."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
