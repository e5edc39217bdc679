"""Zenoh session configuration shared by the server and the clients.

Every configuration turns multicast and gossip scouting off and names its endpoints explicitly
(../shared/notes/zenoh.md section 6: the defaults scout by multicast and listen on all interfaces).

* Server: ``mode: "router"`` listening on its endpoint (a Python session in router mode is a full
  router; there is no separate daemon).
* Clients: ``mode: "client"`` connecting to the server's endpoint.
* Security (optional): user/password authentication (``usrpwd``; the server reads a dictionary file
  of ``user:password`` lines), TLS (``tls/host:port`` endpoints; server certificate and key, client CA),
  and an access-control list generated from the device list: every device may publish and declare
  liveliness only under its own ``hl/v1/*/<device>/**`` keys, query only its own ``locate`` and the
  site maps, and receive only its own ``ack``, ``fix`` and ``track`` and the sites' ``map/version`` and
  ``progress`` announcements (which it may not put: only the server announces). Read-only operator
  users (the dashboard: ``hybridloc dashboard --user operator``) may subscribe to every device's
  ``pose``, ``fix`` and ``track`` and every site's ``progress`` and ``map/version``, and query the
  status and the site maps; never a batch or an ack, and they may put nothing.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import zenoh

from . import protocol as P


@dataclass
class Security:
    users_file: str | None = None  # server: "user:password" per line
    user: str | None = None  # client credentials
    password: str | None = None
    tls_cert: str | None = None  # server certificate (PEM)
    tls_key: str | None = None  # server private key (PEM)
    tls_ca: str | None = None  # client: CA that signed the server certificate
    acl_devices: list[str] = field(default_factory=list)  # server: device user names to confine
    server_user: str = "server"
    #: server, with ``acl_devices``: read-only operator user names (the dashboard's)
    acl_operators: list[str] = field(default_factory=lambda: ["operator"])


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on ``host`` (bind to port 0 and release; a small race remains)."""
    import socket

    s = socket.socket()
    s.bind((host, 0))
    port = s.getsockname()[1]
    s.close()
    return port


def zenoh_reason(exc: BaseException, limit: int = 160, security: Security | None = None) -> str:
    """Zenoh's message for a failed session, for a person: its first line without the source paths it
    appends (``... at /root/.cargo/git/checkouts/zenoh-.../orchestrator.rs:447.``). With credentials
    or a CA in ``security``, a note that a refused login or certificate reads the same: Zenoh says
    "Unable to connect" for all three."""
    lines = str(exc).splitlines() or [""]
    why = lines[0].split(" at /", 1)[0].strip()[:limit]
    if security is not None and (security.user or security.tls_ca):
        why += "; a wrong user, password or CA reads the same"
    return why


def _base(mode: str) -> zenoh.Config:
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    # predictable: our messages are small; no shared-memory path around the size limit
    c.insert_json5("transport/shared_memory/enabled", "false")
    return c


def server_config(endpoint: str, security: Security | None = None, connect: list[str] | None = None) -> zenoh.Config:
    """The server's session: a router listening on ``endpoint``; ``connect``: other servers' routers
    (one mesh: processes serving different sites reach every device). Under user/password
    authentication a connecting router presents ``security.user``/``password`` (the server user)."""
    c = _base("router")
    c.insert_json5("listen/endpoints", json.dumps([endpoint]))
    c.insert_json5("connect/endpoints", json.dumps(list(connect or [])))
    s = security or Security()
    if connect and s.user:
        c.insert_json5("transport/auth/usrpwd/user", json.dumps(s.user))
        c.insert_json5("transport/auth/usrpwd/password", json.dumps(s.password or ""))
    if s.users_file:
        c.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(Path(s.users_file).resolve())))
    if s.tls_cert and s.tls_key:
        c.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(Path(s.tls_cert).resolve())))
        c.insert_json5("transport/link/tls/listen_private_key", json.dumps(str(Path(s.tls_key).resolve())))
    if s.acl_devices:
        c.insert_json5("access_control", json.dumps(acl_for_devices(s.acl_devices, s.server_user, s.acl_operators)))
    return c


def client_config(endpoint: str, security: Security | None = None) -> zenoh.Config:
    c = _base("client")
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("listen/endpoints", "[]")
    s = security or Security()
    if s.user:
        c.insert_json5("transport/auth/usrpwd/user", json.dumps(s.user))
        c.insert_json5("transport/auth/usrpwd/password", json.dumps(s.password or ""))
    if s.tls_ca:
        c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(Path(s.tls_ca).resolve())))
    return c


#: What a read-only operator (the dashboard) hears: every device's pose, fix and corrected track, and
#: every site's progress and new map versions. Never a batch or an ack.
OPERATOR_HEARS = (f"{P.PREFIX}/*/*/pose", f"{P.PREFIX}/*/*/fix", P.SUB_TRACKS, P.SUB_PROGRESS, P.SUB_MAP_VERSIONS)
#: ... and what it may ask: the status and the site maps.
OPERATOR_ASKS = (P.KEY_STATUS, P.SUB_MAPS)


def acl_for_devices(devices: list[str], server_user: str = "server", operators: list[str] | tuple[str, ...] = ()) -> dict:
    """Access control: deny by default; each device confined to its own keys; each operator may only
    listen (:data:`OPERATOR_HEARS`) and ask (:data:`OPERATOR_ASKS`); the server may do all. A name
    that is both (a users file given as the device list holds the operators too) is an operator."""
    operators = [P.check_id(o, "operator") for o in dict.fromkeys(operators) if o != server_user]
    devices = [d for d in devices if d not in operators]
    rules, subjects, policies = [], [], []
    rules.append(
        {
            "id": "all",
            "messages": [
                "put",
                "delete",
                "declare_subscriber",
                "query",
                "reply",
                "declare_queryable",
                "liveliness_token",
                "liveliness_query",
                "declare_liveliness_subscriber",
            ],
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "key_exprs": ["**"],
        }
    )
    subjects.append({"id": "srv", "usernames": [server_user]})
    policies.append({"rules": ["all"], "subjects": ["srv"]})
    for d in devices:
        P.check_id(d, "device")
        rid, sid = f"r_{d}", f"s_{d}"
        rules += [
            {
                "id": f"{rid}_pub",
                "messages": ["put", "liveliness_token"],
                "flows": ["ingress"],
                "permission": "allow",
                "key_exprs": [f"{P.PREFIX}/*/{d}/batch", f"{P.PREFIX}/*/{d}/pose", f"{P.PREFIX}/*/{d}/alive"],
            },
            # the server's batch subscription may be declared to the device. Without it the router hides
            # it; a declared publisher then learns "no subscriber" once the router answers its interest
            # and drops every later put at the device (write-side filtering): a fresh session lost 1-2
            # of 20 first batches, and all batches after the answer. Plain put never filters. The rule
            # names the server's wildcard itself (the router checks the declared key expression: the
            # device's own batch key does not cover it). The device learns only that the key is
            # subscribed, never another device's data.
            {
                "id": f"{rid}_route",
                "messages": ["declare_subscriber"],
                "flows": ["egress"],
                "permission": "allow",
                "key_exprs": [P.SUB_BATCHES],
            },
            {
                "id": f"{rid}_sub",
                "messages": ["declare_subscriber", "put"],
                "flows": ["ingress", "egress"],
                "permission": "allow",
                "key_exprs": [f"{P.PREFIX}/*/{d}/ack", f"{P.PREFIX}/*/{d}/fix"],
            },
            # the server's announcements: the device may subscribe (ingress) and be sent puts (egress),
            # never put them itself, so no device can fake another's track or a site's new map
            {
                "id": f"{rid}_listen",
                "messages": ["declare_subscriber"],
                "flows": ["ingress"],
                "permission": "allow",
                "key_exprs": [f"{P.PREFIX}/*/{d}/track", P.SUB_MAP_VERSIONS, P.SUB_PROGRESS],
            },
            {
                "id": f"{rid}_hear",
                "messages": ["put"],
                "flows": ["egress"],
                "permission": "allow",
                "key_exprs": [f"{P.PREFIX}/*/{d}/track", P.SUB_MAP_VERSIONS, P.SUB_PROGRESS],
            },
            {
                "id": f"{rid}_query",
                "messages": ["query", "reply"],
                "flows": ["ingress", "egress"],
                "permission": "allow",
                "key_exprs": [f"{P.PREFIX}/*/{d}/locate", f"{P.PREFIX}/*/map", P.KEY_STATUS],
            },
        ]
        subjects.append({"id": sid, "usernames": [d]})
        policies.append({"rules": [f"{rid}_pub", f"{rid}_route", f"{rid}_sub", f"{rid}_listen", f"{rid}_hear", f"{rid}_query"], "subjects": [sid]})
    if operators:
        rules += [
            # subscriptions declared by the operator (ingress) and the puts routed to it (egress); the
            # rule names the wildcards the dashboard subscribes with (the router checks the declared key)
            {"id": "op_listen", "messages": ["declare_subscriber"], "flows": ["ingress"], "permission": "allow", "key_exprs": list(OPERATOR_HEARS)},
            {"id": "op_hear", "messages": ["put"], "flows": ["egress"], "permission": "allow", "key_exprs": list(OPERATOR_HEARS)},
            {"id": "op_ask", "messages": ["query"], "flows": ["ingress"], "permission": "allow", "key_exprs": list(OPERATOR_ASKS)},
            {"id": "op_answer", "messages": ["reply"], "flows": ["egress"], "permission": "allow", "key_exprs": list(OPERATOR_ASKS)},
        ]
        subjects.append({"id": "operators", "usernames": operators})
        policies.append({"rules": ["op_listen", "op_hear", "op_ask", "op_answer"], "subjects": ["operators"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}
