"""The clients' retransmission timeout (RFC 6298) and the uplink's use of it: a slow but steady server
gets no flood of resends, a silent one gets resends that back off."""

import threading
import time

import pytest
import zenoh

from hybridloc.types import StepEvent
from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.messages import Ack
from hybridloc.wire.retransmit import ALPHA, BETA, MAX_RTO_S, RetransmitTimer
from hybridloc.wire.zconfig import client_config


def test_first_sample_then_smoothing_as_rfc_6298():
    tm = RetransmitTimer(0.1, max_rto=60.0)
    assert tm.rto == 0.1  # no sample yet: the floor
    tm.sample(1.0)  # (2.2): SRTT = R, RTTVAR = R/2, RTO = SRTT + 4 RTTVAR = 3R
    assert tm.srtt == 1.0 and tm.rttvar == 0.5 and tm.rto == pytest.approx(3.0)
    tm.sample(2.0)  # (2.3)
    rttvar = (1 - BETA) * 0.5 + BETA * abs(1.0 - 2.0)
    srtt = (1 - ALPHA) * 1.0 + ALPHA * 2.0
    assert tm.rttvar == pytest.approx(rttvar) and tm.srtt == pytest.approx(srtt) and tm.rto == pytest.approx(srtt + 4 * rttvar)
    for _ in range(200):  # a steady round trip: the variance decays, the timeout closes on the RTT
        tm.sample(0.5)
    assert tm.srtt == pytest.approx(0.5, rel=1e-6) and tm.rto == pytest.approx(0.5, rel=1e-3)


def test_backoff_doubles_to_the_cap_and_the_floor_holds():
    tm = RetransmitTimer(0.5)
    seen = []
    for _ in range(6):
        tm.backoff()
        seen.append(tm.rto)
    assert seen == [1.0, 2.0, 4.0, 8.0, MAX_RTO_S, MAX_RTO_S]
    tm.sample(0.01)  # a fast ack: back to the floor, never below
    assert tm.rto == 0.5
    zero = RetransmitTimer(0.0)
    zero.backoff()
    assert zero.rto == 0.0  # resend_after=0: resend whenever asked
    tm.sample(float("nan"))
    tm.sample(-1.0)
    assert tm.samples == 1  # no sample from a bad measurement
    with pytest.raises(ValueError):
        RetransmitTimer(float("nan"))


def _steps(t0):
    return [StepEvent(t0 + 0.5 * i, 0.7, 0.0, 0.05, 0.1) for i in range(2)]


def test_uplink_does_not_flood_a_slow_server_and_backs_off_from_a_silent_one(tmp_path):
    """A server answering every batch 0.4 s late (real Zenoh, two peers on a Unix socket) gets each
    batch once after the first ack has set the timer; the old fixed 0.1 s delay would have resent
    everything in flight every 0.1 s. Then the server goes silent: resends back off (0.1 s floor
    doubling), a handful in 3 s instead of 30."""
    from hybridloc.clients.uplink import Uplink

    sock = f"unixsock-stream/{tmp_path}/up.sock"
    lconf = client_config(sock)
    lconf.insert_json5("mode", '"peer"')
    lconf.insert_json5("connect/endpoints", "[]")
    lconf.insert_json5("listen/endpoints", f'["{sock}"]')
    cconf = client_config(sock)
    cconf.insert_json5("mode", '"peer"')
    got: list[int] = []
    answering = threading.Event()
    answering.set()
    timers: list[threading.Timer] = []
    with zenoh.open(lconf) as srv, zenoh.open(cconf) as cli:

        def on_batch(sample):
            b = C.BATCH.decode(sample.payload.to_bytes())
            got.append(b.seq)
            if answering.is_set():
                t = threading.Timer(0.4, lambda: srv.put(P.key_ack("site1", "slow"), C.ACK.encode(Ack("slow", b.seq))))
                timers.append(t)
                t.start()

        sub = srv.declare_subscriber(P.key_batch("site1", "slow"), on_batch)
        up = Uplink(cli, "site1", "slow", tmp_path / "spool", resend_after=0.1)
        try:
            deadline = time.monotonic() + 10
            while not got and time.monotonic() < deadline:  # the route is up once a batch arrives
                up.send(steps=_steps(0.0))
                up.wait_acked(timeout=1.0)
            # the first batches were resent before their late acks (Karn: no sample from them) and the
            # timeout backed off meanwhile
            assert up.wait_acked(timeout=10)
            before = up.n_resent
            for k in range(10):  # a batch every 0.2 s, each acknowledged 0.4 s later: 2 in flight
                up.send(steps=_steps(10.0 + k))
                t_end = time.monotonic() + 0.2
                while time.monotonic() < t_end:
                    up.resend_if_stalled()
                    time.sleep(0.01)
            assert up.wait_acked(timeout=10) and up.timer.samples >= 1
            # at most one early resend while the timer learns (a fixed 0.1 s delay: one per ack gap, ~20)
            assert up.n_resent - before <= 2, f"{up.n_resent - before} resends to a server that answered every batch"
            answering.clear()  # silent now
            up.send(steps=_steps(30.0))
            n0, t_end = up.n_resent, time.monotonic() + 3.0
            while time.monotonic() < t_end:
                up.resend_if_stalled()
                time.sleep(0.01)
            # RTO >= 0.4 s after the steady 0.4 s acks (SRTT ~ 0.4 s + 4 RTTVAR), doubling after each
            # resend (0.4 + 0.8 + 1.6 s): at most 3 resends in 3 s (a fixed 0.1 s delay: 30)
            assert 1 <= up.n_resent - n0 <= 3
        finally:
            answering.clear()
            for t in timers:
                t.cancel()
                t.join()
            up.close()
            sub.undeclare()
