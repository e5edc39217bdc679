"""``hybridloc status``: ask a running server for its status over Zenoh."""

from __future__ import annotations

import zenoh

from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.zconfig import Security, client_config, zenoh_reason


def query_status(endpoint: str, security: Security | None = None, timeout: float = 5.0) -> dict | None:
    """The server's status as the message's dict (schema, online, counts, db, maps_loaded, slam, sites;
    validated by :data:`hybridloc.wire.codecs.STATUS`); None when no server answers. Several server
    processes on one mesh: the first to answer (:func:`query_statuses` gives them all)."""
    every = query_statuses(endpoint, security, timeout)
    return every[0] if every else None


def query_statuses(endpoint: str, security: Security | None = None, timeout: float = 5.0) -> list[dict]:
    """Every server process's status (the query goes to all queryables, not the nearest one)."""
    out = []
    try:
        session = zenoh.open(client_config(endpoint, security))
    except zenoh.ZError as exc:  # nothing listens there (or it refused us): the user's to mend, in one line
        raise OSError(f"cannot reach the server at {endpoint}: {zenoh_reason(exc, security=security)}") from None
    with session as s:
        for r in s.get(P.KEY_STATUS, timeout=timeout, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE):
            if r.ok:
                out.append({"schema": C.STATUS.schema, **C.STATUS.decode(r.ok.payload.to_bytes()).as_dict()})
    return out
