"""Process pools for the batch work of commands (reading many walks, replaying clients) that a Ctrl-C
stops at once and cleanly.

A terminal's Ctrl-C reaches the whole process group. Left alone, every worker dies of its own
KeyboardInterrupt, and the pool's exit still waits for the work queued behind them (``slam run``
took about 25 s to stop while reading site1's walks). Here the workers ignore SIGINT, so only the
command's process takes it; the pool then cancels what has not started and waits only for what is
running (one task per worker).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import signal
from collections.abc import Iterator


def ignore_sigint() -> None:
    """A pool worker's initializer: SIGINT is the command's to handle, not the worker's."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def process_pool(workers: int, mp_context=None) -> Iterator[cf.ProcessPoolExecutor]:
    """A :class:`concurrent.futures.ProcessPoolExecutor` of ``workers`` processes whose workers ignore
    SIGINT; on any exception in the block (a Ctrl-C, a failed task) the tasks not yet started are
    cancelled before the pool is shut down."""
    ex = cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp_context, initializer=ignore_sigint)
    try:
        yield ex
    except BaseException:
        ex.shutdown(wait=True, cancel_futures=True)
        raise
    ex.shutdown(wait=True)
