"""``hybridloc status``: ask a running server for its status over Zenoh."""

from __future__ import annotations

import json

import zenoh

from hybridloc.wire import protocol as P
from hybridloc.wire.zconfig import Security, client_config


def query_status(endpoint: str, security: Security | None = None, timeout: float = 5.0) -> dict | None:
    with zenoh.open(client_config(endpoint, security)) as s:
        for r in s.get(P.KEY_STATUS, timeout=timeout):
            if r.ok:
                return json.loads(r.ok.payload.to_bytes())
    return None
