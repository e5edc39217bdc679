"""The conftest safety net records sessions; a loopback pair proves the stack works here."""

import json
import threading

import zenoh


def _conf(mode, listen=(), connect=()):
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("listen/endpoints", json.dumps(list(listen)))
    c.insert_json5("connect/endpoints", json.dumps(list(connect)))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    return c


def test_loopback_pair_and_net_records_sessions(tmp_path):
    import tests.conftest as cf

    ep = f"unixsock-stream/{tmp_path}/z.sock"
    before = len(cf._sessions)
    a = zenoh.open(_conf("peer", listen=[ep]))
    b = zenoh.open(_conf("peer", connect=[ep]))
    try:
        assert len(cf._sessions) == before + 2
        got = threading.Event()
        sub = a.declare_subscriber("hl/test/**", lambda s: got.set())
        pub = b.declare_publisher("hl/test/x", congestion_control=zenoh.CongestionControl.BLOCK)
        for _ in range(200):
            if pub.matching_status.matching:
                break
            threading.Event().wait(0.01)
        pub.put(b"hi")
        assert got.wait(5.0)
        sub.undeclare()
        pub.undeclare()
    finally:
        b.close()
        a.close()
