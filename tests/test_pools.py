"""hybridloc.pools: process pools that a Ctrl-C stops at once (workers ignore SIGINT, queued tasks cancelled)."""

from __future__ import annotations

import signal
import time

import pytest

from hybridloc.pools import process_pool


def _sigint_handler(_: int) -> bool:
    return signal.getsignal(signal.SIGINT) == signal.SIG_IGN


def _nap(s: float) -> float:
    time.sleep(s)
    return s


def test_workers_ignore_sigint():
    with process_pool(2) as ex:
        assert all(ex.map(_sigint_handler, range(4)))


def test_an_interrupt_cancels_the_tasks_not_started():
    """A KeyboardInterrupt in the block (what Ctrl-C raises in the command's process): the 40 tasks
    queued behind the 2 running ones are cancelled, not run before the pool lets go."""
    futs = []
    with pytest.raises(KeyboardInterrupt):
        with process_pool(2) as ex:
            futs = [ex.submit(_nap, 0.2) for _ in range(42)]
            futs[0].result()
            raise KeyboardInterrupt
    # not cancelled: the one done, the 2 running, the pool's call queue (workers + 1 = 3,
    # concurrent.futures' EXTRA_QUEUED_CALLS), and what the 2 workers finish while the cancel lands
    # (a task is 0.2 s: 10 in a second of a loaded machine); without the cancel, all 42 run first
    assert sum(f.cancelled() for f in futs) >= 42 - 1 - 2 - 3 - 10
