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
``hl/v1/<site>/<device>/track``                server -> client (put)   ``hybridloc.track/1``
``hl/v1/<site>/map``                           client -> server (get)   -> radio map file (npz bytes)
``hl/v1/<site>/map/version``                   server -> clients (put)  ``hybridloc.map-version/1``
``hl/v1/<site>/progress``                      server -> anyone (put)   ``hybridloc.progress/1``
``hl/v1/status``                               anyone -> server (get)   -> ``hybridloc.status/1``
=============================================  ======================  ==============================

``track`` carries the crowd SLAM's corrected track of the device's current walk (the newest
:data:`MAX_TRACK_POINTS` points); ``map/version`` announces each new radio map version of a site (a
client then fetches it with a get on ``map``: ``hl/v1/*/map`` does not match ``map/version``, one chunk
more); ``progress`` reports a running SLAM job (stage, floor, done of total).

Batches carry a per-device sequence number starting at 1. The server persists batch ``n`` only when
``n - 1`` is persisted (go-back-N): a lower or equal number is a ``duplicate`` (acknowledged again), a
higher one is ``out-of-order`` (rejected; the ack tells the client where to resume). After persisting,
the server publishes the highest persisted sequence number on the device's ``ack`` key.

Every message's bytes come from one symmetric codec in :mod:`.codecs` (``encode(record) -> bytes``,
``decode(bytes) -> record``; validation in the decoders, refusals as :class:`Rejected`); the records
are in :mod:`hybridloc.types` and :mod:`.messages`.
"""

from __future__ import annotations

import re
import warnings

from .messages import Batch  # noqa: F401 - the batch record, importable from here as it always was

PREFIX = "hl/v1"
BATCH_SCHEMA = "hybridloc.batch/1"
ACK_SCHEMA = "hybridloc.ack/1"
FIX_SCHEMA = "hybridloc.fix/1"
POSE_SCHEMA = "hybridloc.pose/1"
LOCATE_SCHEMA = "hybridloc.locate/1"
STATUS_SCHEMA = "hybridloc.status/1"
TRACK_SCHEMA = "hybridloc.track/1"
MAP_VERSION_SCHEMA = "hybridloc.map-version/1"
PROGRESS_SCHEMA = "hybridloc.progress/1"

#: Largest accepted batch payload, bytes, and item count per batch.
MAX_BATCH_BYTES = 256 * 1024
MAX_BATCH_ITEMS = 2000

#: Largest corrected track on the wire, points: 10,000 is 80 minutes of walking at 2 steps/s plus a
#: scan every 2 s; the encoder sends the newest points of a longer walk (what re-anchoring uses).
MAX_TRACK_POINTS = 10_000
#: Largest accepted track payload, bytes. A point is at most ~200 bytes of JSON (t, x, y: 24
#: characters each at most; a covariance of three more; its kind; a run of a 32-character floor when
#: every point changes floor), so MAX_TRACK_POINTS fit in 2 MB; the encoder drops the oldest points
#: of a payload that would still be larger (floor names of escaped non-ASCII characters).
MAX_TRACK_BYTES = 4 * 1024 * 1024

_ID = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


def encoding(schema: str) -> str:
    return f"application/json;schema={schema}"


def check_id(value: object, what: str = "id") -> str:
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


def key_track(site: str, device: str) -> str:
    """The device's corrected track (server put, ``hybridloc.track/1``)."""
    return f"{PREFIX}/{check_id(site, 'site')}/{check_id(device, 'device')}/track"


def key_map_version(site: str) -> str:
    """New radio map versions of the site (server put, ``hybridloc.map-version/1``)."""
    return f"{PREFIX}/{check_id(site, 'site')}/map/version"


def key_progress(site: str) -> str:
    """The site's running SLAM job (server put, ``hybridloc.progress/1``)."""
    return f"{PREFIX}/{check_id(site, 'site')}/progress"


KEY_STATUS = f"{PREFIX}/status"


def sub_batches(site: str) -> str:
    """Every device's batches of one site (a server process serving only some sites)."""
    return f"{PREFIX}/{check_id(site, 'site')}/*/batch"


def sub_locate(site: str) -> str:
    """Every device's locate queries of one site."""
    return f"{PREFIX}/{check_id(site, 'site')}/*/locate"


SUB_BATCHES = f"{PREFIX}/*/*/batch"
SUB_LOCATE = f"{PREFIX}/*/*/locate"
SUB_MAPS = f"{PREFIX}/*/map"  # the map queryable: one chunk short of every map/version key
SUB_ALIVE = f"{PREFIX}/*/*/alive"
SUB_TRACKS = f"{PREFIX}/*/*/track"
SUB_MAP_VERSIONS = f"{PREFIX}/*/map/version"
SUB_PROGRESS = f"{PREFIX}/*/progress"


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


# ---------------------------------------------------------------------------------------------- deprecated
def _encode_batch(site: str, device: str, seq: int, steps=(), scans=(), marks=(), device_model: str = "", sent_at: float = 0.0) -> bytes:
    from .codecs import BATCH

    return BATCH.encode(Batch(site, device, seq, device_model, steps, scans, marks, sent_at))


def _decode_batch(payload: bytes, key_site: str | None = None, key_device: str | None = None) -> Batch:
    from .codecs import BATCH

    return BATCH.decode(payload, key_site, key_device)


def _encode_ack(device: str, seq: int) -> bytes:
    from .codecs import ACK
    from .messages import Ack

    return ACK.encode(Ack(device, seq))


def _decode_ack(payload: bytes) -> int:
    from .codecs import ACK

    return ACK.decode(payload).acked_seq


def _fix_to_dict(fix, region=None, reason: str = "", t: float | None = None) -> dict:
    import json

    from ..types import Fix
    from .codecs import FIX

    return json.loads(FIX.encode(Fix(None, reason=reason, t=t) if fix is None else Fix(fix, region)))


def _fix_from_dict(d: dict):
    import json

    from .codecs import FIX

    a = FIX.decode(json.dumps(d).encode())
    return a.fix, (d.get("region") if a.fix is not None else None), a.reason


def _deprecated():
    from ..types import RfScan, SurveyMark
    from .codecs import step_to_dict

    return {
        "ScanRecord": (RfScan, "hybridloc.types.RfScan (rssi_dbm, frequency_hz, age_s)"),
        "MarkRecord": (SurveyMark, "hybridloc.types.SurveyMark"),
        "encode_batch": (_encode_batch, "hybridloc.wire.codecs.BATCH.encode(Batch(...))"),
        "decode_batch": (_decode_batch, "hybridloc.wire.codecs.BATCH.decode(payload, site, device)"),
        "encode_ack": (_encode_ack, "hybridloc.wire.codecs.ACK.encode(Ack(device, seq))"),
        "decode_ack": (_decode_ack, "hybridloc.wire.codecs.ACK.decode(payload).acked_seq"),
        "fix_to_dict": (_fix_to_dict, "hybridloc.wire.codecs.FIX.encode(Fix(...))"),
        "fix_from_dict": (_fix_from_dict, "hybridloc.wire.codecs.FIX.decode(payload)"),
        "step_to_dict": (step_to_dict, "hybridloc.wire.codecs.step_to_dict"),
    }


_DEPRECATED = ("ScanRecord", "MarkRecord", "encode_batch", "decode_batch", "encode_ack", "decode_ack", "fix_to_dict", "fix_from_dict", "step_to_dict")


def __getattr__(name: str):
    """The names this module had before the codecs, still importable (with a DeprecationWarning)."""
    if name not in _DEPRECATED:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    obj, use = _deprecated()[name]
    warnings.warn(f"hybridloc.wire.protocol.{name} is deprecated: use {use}", DeprecationWarning, stacklevel=2)
    return obj
