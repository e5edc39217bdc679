"""``hybridloc status``: ask a running server for its status over Zenoh."""

from __future__ import annotations

import zenoh

from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.zconfig import Security, client_config


def query_status(endpoint: str, security: Security | None = None, timeout: float = 5.0) -> dict | None:
    """The server's status as the message's dict (schema, online, counts, db, maps_loaded, slam; validated
    by :data:`hybridloc.wire.codecs.STATUS`); None when no server answers."""
    with zenoh.open(client_config(endpoint, security)) as s:
        for r in s.get(P.KEY_STATUS, timeout=timeout):
            if r.ok:
                return {"schema": C.STATUS.schema, **C.STATUS.decode(r.ok.payload.to_bytes()).as_dict()}
    return None
