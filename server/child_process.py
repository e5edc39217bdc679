"""What every process the server spawns does first (the SLAM child, :mod:`.slam_child`; the locate
workers, :mod:`.locate_pool`): it yields to the server, and it ends when the server is gone."""

from __future__ import annotations

import os
import threading
import time


def _watch_parent(parent_pid: int) -> None:
    while True:
        if os.getppid() != parent_pid:
            os._exit(1)  # the server is gone (SIGKILL): nothing of ours is left to do; what it stored is safe
        time.sleep(0.5)


def yield_to_server(parent_pid: int, niceness: int, name: str) -> None:
    """A lower CPU priority (``niceness`` more), one BLAS thread (OpenBLAS takes every core by default),
    and a thread ``name`` that exits this process once ``parent_pid`` is no longer its parent."""
    from threadpoolctl import threadpool_limits

    os.nice(niceness)
    threadpool_limits(1)
    threading.Thread(target=_watch_parent, args=(parent_pid,), name=name, daemon=True).start()
