"""The wire contract between clients and server: key expressions, message schemas, limits, validation.

Documented in docs/protocol.md. Both ``hybridloc.server`` and ``hybridloc.clients`` use this module;
neither imports the other. Payloads are JSON (UTF-8) with encoding ``application/json;schema=<name>/<v>``.

Key expressions (``<site>`` and ``<device>`` are single chunks, see :func:`check_id`):

=============================================  ======================  ==============================
key                                            direction               payload
=============================================  ======================  ==============================
``hl/v1/<site>/<device>/batch``                client -> server (put)   ``hybridloc.batch/1``
``hl/v1/<site>/<device>/ack``                  server -> client (put)   ``hybridloc.ack/1``
``hl/v1/<site>/<device>/fix``                  server -> client (put)   ``hybridloc.fix/1``
``hl/v1/<site>/<device>/pose``                 client -> anyone (put)   ``hybridloc.pose/1``
``hl/v1/<site>/<device>/alive``                liveliness token         (none)
``hl/v1/<site>/<device>/locate``               client -> server (get)   ``hybridloc.locate/1`` -> ``fix/1``
``hl/v1/<site>/map``                           client -> server (get)   -> radio map file (npz bytes)
``hl/v1/status``                               anyone -> server (get)   -> ``hybridloc.status/1``
=============================================  ======================  ==============================

Batches carry a per-device sequence number starting at 1. The server persists batch ``n`` only when
``n - 1`` is persisted (go-back-N): a lower or equal number is a ``duplicate`` (acknowledged again), a
higher one is ``out-of-order`` (rejected; the ack tells the client where to resume). After persisting,
the server publishes the highest persisted sequence number on the device's ``ack`` key.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field

from ..types import RSSI_MAX_DBM, RSSI_MIN_DBM, StepEvent

PREFIX = "hl/v1"
BATCH_SCHEMA = "hybridloc.batch/1"
ACK_SCHEMA = "hybridloc.ack/1"
FIX_SCHEMA = "hybridloc.fix/1"
POSE_SCHEMA = "hybridloc.pose/1"
LOCATE_SCHEMA = "hybridloc.locate/1"
STATUS_SCHEMA = "hybridloc.status/1"

#: Largest accepted batch payload, bytes, and item count per batch.
MAX_BATCH_BYTES = 256 * 1024
MAX_BATCH_ITEMS = 2000

_ID = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


def encoding(schema: str) -> str:
    return f"application/json;schema={schema}"


def check_id(value: str, what: str = "id") -> str:
    """Site and device ids are 1-64 characters of [A-Za-z0-9_.-] (one key-expression chunk)."""
    if not isinstance(value, str) or not _ID.match(value):
        raise ValueError(f"invalid {what} {value!r}: 1-64 characters of letters, digits, '_', '.', '-'")
    return value


def key_batch(site: str, device: str) -> str:
    return f"{PREFIX}/{check_id(site, 'site')}/{check_id(device, 'device')}/batch"


def key_ack(site: str, device: str) -> str:
    return f"{PREFIX}/{site}/{device}/ack"


def key_fix(site: str, device: str) -> str:
    return f"{PREFIX}/{site}/{device}/fix"


def key_pose(site: str, device: str) -> str:
    return f"{PREFIX}/{site}/{device}/pose"


def key_alive(site: str, device: str) -> str:
    return f"{PREFIX}/{site}/{device}/alive"


def key_locate(site: str, device: str) -> str:
    return f"{PREFIX}/{site}/{device}/locate"


def key_map(site: str) -> str:
    return f"{PREFIX}/{check_id(site, 'site')}/map"


KEY_STATUS = f"{PREFIX}/status"
SUB_BATCHES = f"{PREFIX}/*/*/batch"
SUB_LOCATE = f"{PREFIX}/*/*/locate"
SUB_MAPS = f"{PREFIX}/*/map"
SUB_ALIVE = f"{PREFIX}/*/*/alive"


def parse_key(key: str) -> tuple[str, str, str]:
    """(site, device, kind) of a per-device key; ValueError otherwise."""
    parts = str(key).split("/")
    if len(parts) != 5 or "/".join(parts[:2]) != PREFIX:
        raise ValueError(f"not a hybridloc device key: {key!r}")
    return check_id(parts[2], "site"), check_id(parts[3], "device"), parts[4]


class Rejected(ValueError):
    """A message refused for a stable, countable ``reason``."""

    def __init__(self, reason: str, detail: str = ""):
        self.reason = reason
        super().__init__(f"{reason}: {detail}" if detail else reason)


@dataclass(frozen=True)
class ScanRecord:
    t: float
    technology: str
    rssi: dict
    frequency: dict = field(default_factory=dict)
    age: dict = field(default_factory=dict)  # transmitter -> seconds since the reading was taken (Android's cache)


@dataclass(frozen=True)
class MarkRecord:
    """A survey mark: the operator says "I am at (x, y) on floor" at time t."""

    t: float
    x: float
    y: float
    floor: str


@dataclass(frozen=True)
class Batch:
    site: str
    device: str
    seq: int
    device_model: str
    steps: tuple[StepEvent, ...]
    scans: tuple[ScanRecord, ...]
    marks: tuple[MarkRecord, ...]
    sent_at: float

    def to_json(self) -> bytes:
        return encode_batch(self.site, self.device, self.seq, self.steps, self.scans, self.marks, self.device_model, self.sent_at)


def _finite(v, what: str) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise Rejected("bad-value", f"{what} is not a number") from None
    if not math.isfinite(x):
        raise Rejected("non-finite", what)
    return x


def step_to_dict(s: StepEvent) -> dict:
    d = {"t": s.t, "length": s.length, "heading": s.heading, "sigma_length": s.sigma_length, "sigma_heading": s.sigma_heading}
    if s.heading_change is not None:
        d["heading_change"] = s.heading_change
        d["sigma_heading_change"] = s.sigma_heading_change
    if s.height_change:
        d["height_change"] = s.height_change
        d["sigma_height_change"] = s.sigma_height_change
    if s.floor_change:
        d["floor_change"] = s.floor_change
    if s.degraded:
        d["degraded"] = s.degraded
    return d


def encode_batch(site: str, device: str, seq: int, steps=(), scans=(), marks=(), device_model: str = "", sent_at: float = 0.0) -> bytes:
    msg = {
        "schema": BATCH_SCHEMA, "site": site, "device": device, "seq": int(seq), "device_model": device_model, "sent_at": sent_at,
        "steps": [step_to_dict(s) for s in steps],
        "scans": [{"t": s.t, "tech": s.technology, "rssi": dict(s.rssi), **({"freq": dict(s.frequency)} if s.frequency else {}),
                   **({"age": dict(s.age)} if s.age else {})} for s in scans],
        "marks": [{"t": m.t, "x": m.x, "y": m.y, "floor": m.floor} for m in marks],
    }
    return json.dumps(msg, separators=(",", ":"), allow_nan=False).encode("utf-8")


def decode_batch(payload: bytes, key_site: str | None = None, key_device: str | None = None) -> Batch:
    """Validate a batch payload; raise :class:`Rejected` with a countable reason otherwise."""
    if len(payload) > MAX_BATCH_BYTES:
        raise Rejected("too-large", f"{len(payload)} bytes > {MAX_BATCH_BYTES}")
    try:
        msg = json.loads(payload.decode("utf-8"), parse_constant=lambda c: (_ for _ in ()).throw(Rejected("non-finite", c)))
    except Rejected:
        raise
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise Rejected("malformed-json", str(exc)[:80]) from None
    if not isinstance(msg, dict):
        raise Rejected("malformed-json", "not an object")
    if msg.get("schema") != BATCH_SCHEMA:
        raise Rejected("schema-version", f"expected {BATCH_SCHEMA}, got {msg.get('schema')!r}")
    try:
        site, device = check_id(msg.get("site"), "site"), check_id(msg.get("device"), "device")
    except ValueError as exc:
        raise Rejected("bad-id", str(exc)) from None
    if (key_site is not None and site != key_site) or (key_device is not None and device != key_device):
        raise Rejected("key-mismatch", f"payload says {site}/{device}, key says {key_site}/{key_device}")
    seq = msg.get("seq")
    if not isinstance(seq, int) or isinstance(seq, bool) or seq < 1:
        raise Rejected("bad-seq", repr(seq))
    steps_in, scans_in, marks_in = msg.get("steps") or [], msg.get("scans") or [], msg.get("marks") or []
    if not all(isinstance(x, list) for x in (steps_in, scans_in, marks_in)):
        raise Rejected("malformed-json", "steps, scans and marks must be lists")
    if len(steps_in) + len(scans_in) + len(marks_in) > MAX_BATCH_ITEMS:
        raise Rejected("too-large", f"more than {MAX_BATCH_ITEMS} items")
    steps = []
    try:
        for s in steps_in:
            hc = s.get("heading_change")
            steps.append(StepEvent(
                _finite(s["t"], "step t"), _finite(s["length"], "length"), _finite(s["heading"], "heading"),
                _finite(s["sigma_length"], "sigma_length"), _finite(s["sigma_heading"], "sigma_heading"),
                None if hc is None else _finite(hc, "heading_change"),
                None if s.get("sigma_heading_change") is None else _finite(s["sigma_heading_change"], "sigma_heading_change"),
                _finite(s.get("height_change", 0.0), "height_change"), _finite(s.get("sigma_height_change", 0.0), "sigma_height_change"),
                int(s.get("floor_change", 0)), str(s.get("degraded", ""))[:32],
            ))
        scans = []
        for s in scans_in:
            rssi = s["rssi"]
            if not isinstance(rssi, dict) or not rssi:
                raise Rejected("bad-scan", "rssi must be a non-empty object")
            clean = {}
            for k, v in rssi.items():
                r = _finite(v, "rssi")
                if not RSSI_MIN_DBM <= r <= RSSI_MAX_DBM:
                    raise Rejected("rssi-out-of-range", f"{r} dBm")
                clean[str(k)[:64]] = r
            tech = s.get("tech", "wifi")
            if tech not in ("wifi", "ble", "rfid"):
                raise Rejected("bad-scan", f"technology {tech!r}")
            freq = {str(k)[:64]: _finite(v, "freq") for k, v in (s.get("freq") or {}).items()}
            age = {str(k)[:64]: _finite(v, "age") for k, v in (s.get("age") or {}).items()}
            scans.append(ScanRecord(_finite(s["t"], "scan t"), tech, clean, freq, age))
        marks = [MarkRecord(_finite(m["t"], "mark t"), _finite(m["x"], "x"), _finite(m["y"], "y"), str(m.get("floor", ""))[:32]) for m in marks_in]
    except Rejected:
        raise
    except (KeyError, TypeError, AttributeError) as exc:
        raise Rejected("malformed-json", f"missing or wrong field {exc}") from None
    except ValueError as exc:  # StepEvent's own checks (negative sigma ...)
        raise Rejected("bad-value", str(exc)) from None
    return Batch(site, device, seq, str(msg.get("device_model", ""))[:64], tuple(steps), tuple(scans), tuple(marks), float(msg.get("sent_at") or 0.0))


def encode_ack(device: str, seq: int) -> bytes:
    return json.dumps({"schema": ACK_SCHEMA, "device": device, "acked_seq": int(seq)}).encode()


def decode_ack(payload: bytes) -> int:
    msg = json.loads(payload)
    if msg.get("schema") != ACK_SCHEMA:
        raise ValueError("not an ack")
    return int(msg["acked_seq"])


def fix_to_dict(fix, region=None, reason: str = "", t: float | None = None) -> dict:
    """A fix message; with ``fix`` None a "no fix" answer giving ``reason`` (and the scan time ``t``)."""
    if fix is None:
        d = {"schema": FIX_SCHEMA, "fix": None, "reason": reason}
        if t is not None:
            d["t"] = float(t)
        return d
    d = {"schema": FIX_SCHEMA, "fix": {"t": fix.t, "x": float(fix.pos_enu[0]), "y": float(fix.pos_enu[1]), "cov": fix.cov[:2, :2].tolist(),
                                       "floor": fix.floor, "floor_prob": fix.floor_prob, "source": fix.source.value}}
    if region is not None:
        from shapely.geometry import mapping

        d["region"] = {"floor": region.floor, "mass": region.mass, "geometry": mapping(region.area)}
    return d


def fix_from_dict(d: dict):
    """(AbsoluteFix or None, region geometry dict or None, reason)."""
    from ..types import AbsoluteFix

    if d.get("schema") != FIX_SCHEMA:
        raise ValueError("not a fix message")
    f = d.get("fix")
    if f is None:
        return None, None, d.get("reason", "")
    fix = AbsoluteFix(float(f["t"]), [f["x"], f["y"]], f["cov"], f["source"], f.get("floor"), float(f.get("floor_prob", 1.0)))
    return fix, d.get("region"), ""
