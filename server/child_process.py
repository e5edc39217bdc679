"""What every process the server spawns does first (the SLAM child, :mod:`.slam_child`; the locate
workers, :mod:`.locate_pool`; the ingest workers, :mod:`.ingest_pool`): it yields to the server, it
leaves Ctrl-C to the server, and it ends when the server is gone."""

from __future__ import annotations

import os
import threading
import time

from hybridloc.pools import ignore_sigint


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity, else the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


def _watch_parent(parent_pid: int) -> None:
    while True:
        if os.getppid() != parent_pid:
            os._exit(1)  # the server is gone (SIGKILL): nothing of ours is left to do; what it stored is safe
        time.sleep(0.5)


def yield_to_server(parent_pid: int, niceness: int, name: str) -> None:
    """A lower CPU priority (``niceness`` more), one BLAS thread (OpenBLAS takes every core by default),
    SIGINT ignored, and a thread ``name`` that exits this process once ``parent_pid`` is no longer its
    parent. Ctrl-C at a terminal reaches the whole process group: the server alone decides how its
    children stop (an ingest worker stores and acknowledges what it was sent first), where a
    KeyboardInterrupt would have cut each one off mid-task with a traceback. Call it from the child's
    main thread."""
    from threadpoolctl import threadpool_limits

    ignore_sigint()
    os.nice(niceness)
    threadpool_limits(1)
    threading.Thread(target=_watch_parent, args=(parent_pid,), name=name, daemon=True).start()
