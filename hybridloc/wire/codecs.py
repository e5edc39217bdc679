"""One symmetric codec per wire message: ``encode(record) -> bytes``, ``decode(bytes) -> record``.

=====================  ===========================  =====================================================
codec                  record                       message
=====================  ===========================  =====================================================
:data:`BATCH`          :class:`.messages.Batch`     ``hybridloc.batch/1``, client -> server
:data:`ACK`            :class:`.messages.Ack`       ``hybridloc.ack/1``, server -> client
:data:`FIX`            :class:`~hybridloc.types.Fix`  ``hybridloc.fix/1``, server -> client (push, locate reply)
:data:`POSE`           :class:`~hybridloc.types.Pose`  ``hybridloc.pose/1``, client -> anyone
:data:`LOCATE`         :class:`.messages.LocateRequest`  ``hybridloc.locate/1``, client -> server (get)
:data:`STATUS`         :class:`.messages.Status`    ``hybridloc.status/1``, server reply
:data:`MAP_INFO`       :class:`.messages.MapInfo`   the attachment of a ``map`` reply (its payload is npz bytes)
:data:`TRACK`          :class:`.messages.Track`     ``hybridloc.track/1``, server -> client
:data:`MAP_VERSION`    :class:`.messages.MapVersion`  ``hybridloc.map-version/1``, server -> clients
:data:`PROGRESS`       :class:`.messages.Progress`  ``hybridloc.progress/1``, server -> anyone
=====================  ===========================  =====================================================

Validation lives in the decoders, and only there: a refused payload raises
:class:`~.protocol.Rejected` with a stable, countable reason (listed in docs/protocol.md); nothing else
escapes a decoder, whatever the bytes. Encoders trust their records.

A batch's steps may also travel in a columnar form (a list per field, ``BATCH.encode(b, step_columns=True)``,
docs/protocol.md "Step columns"), which the decoder reads as the rows it stands for, through the same
checks; decoded steps are held as :class:`~.messages.StepColumns` (made into records only when read).

The bytes are the ones hybridloc has always sent, so old clients and spooled batches keep working:
JSON in UTF-8, a batch and a track with compact separators (``","``, ``":"``), every other message
with ``json.dumps``' defaults (``", "``, ``": "``), keys in the order below. Optional keys are left out
when empty. A few records cannot say everything their types can: a step's ``sigma_height_change``
travels only with a non-zero ``height_change`` and ``sigma_heading_change`` only with a
``heading_change``; transmitter ids and the device model are cut at 64 characters, a mark's floor and ``degraded``
at 32; a fix is 2-D; a region's time is its fix's; a track carries the upper triangle of each
covariance (null for one that is not finite: all four entries NaN again) and its newest
:data:`~.protocol.MAX_TRACK_POINTS` points, floors cut at 32 characters; a progress's stage and floor
are cut at 32 characters.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any, Generic, TypeVar

import msgspec
import numpy as np

from ..types import (
    TRACK_ANCHORS,
    AbsoluteFix,
    ContainmentRegion,
    CorrectedTrack,
    Fix,
    Pose,
    RfScan,
    StepEvent,
    SurveyMark,
    Technology,
    rssi_in_range,
)
from ..units import wrap_angle
from . import limits
from .messages import MAP_SOURCES, Ack, Batch, LocateRequest, MapInfo, MapVersion, Progress, Status, StepColumns, Track
from .protocol import (
    ACK_SCHEMA,
    BATCH_SCHEMA,
    FIX_SCHEMA,
    LOCATE_SCHEMA,
    MAP_VERSION_SCHEMA,
    MAX_BATCH_BYTES,
    MAX_BATCH_ITEMS,
    MAX_TRACK_BYTES,
    MAX_TRACK_POINTS,
    POSE_SCHEMA,
    PROGRESS_SCHEMA,
    STATUS_SCHEMA,
    TRACK_SCHEMA,
    Rejected,
    check_id,
    encoding,
)

R = TypeVar("R")

#: Largest accepted locate or pose payload, bytes (what a batch may be).
MAX_MESSAGE_BYTES = MAX_BATCH_BYTES


# ---------------------------------------------------------------------------------------------- decoding helpers
def _reject_constant(name: str):
    raise Rejected("non-finite", name)


def _load(payload: bytes, schema: str | None, max_bytes: int | None = None) -> dict:
    """The JSON object of ``payload`` whose ``schema`` is ``schema`` (None: no schema key)."""
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise Rejected("malformed-json", f"payload is {type(payload).__name__}, not bytes")
    payload = bytes(payload)
    if max_bytes is not None and len(payload) > max_bytes:
        raise Rejected("too-large", f"{len(payload)} bytes > {max_bytes}")
    try:
        # msgspec reads strict JSON (no NaN or Infinity literals, integers exact up to json's 4,300
        # digits) several times faster than json; what it refuses (NaN, overflowing literals, bad
        # UTF-8, deep nesting ...) is read again by the standard parser, which names every
        # refusal's reason. So the messages accepted and the reasons are json's.
        msg = msgspec.json.decode(payload)
    except (msgspec.DecodeError, RecursionError):
        msg = _load_slow(payload)
    if not isinstance(msg, dict):
        raise Rejected("malformed-json", "not an object")
    if schema is not None and msg.get("schema") != schema:
        raise Rejected("schema-version", f"expected {schema}, got {msg.get('schema')!r}")
    return msg


def _load_slow(payload: bytes):
    try:
        msg = json.loads(payload.decode("utf-8"), parse_constant=_reject_constant)  # NaN, Infinity, -Infinity
    except Rejected:
        raise
    except (ValueError, RecursionError) as exc:  # bad UTF-8 or JSON, an integer past Python's digit limit, nesting too deep
        raise Rejected("malformed-json", str(exc)[:80]) from None
    # json reads an escaped lone surrogate ("\ud800") into a string no UTF-8 can hold (msgspec refuses
    # it): such a string, stored, failed the database's encoding and rolled back its whole group of
    # batches, other devices' included. Refused as the fast parser refuses it.
    if _SURROGATE_ESCAPE.search(payload) and not _utf8_text(msg):
        raise Rejected("malformed-json", "a string with a lone surrogate (not Unicode text)")
    return msg


_SURROGATE_ESCAPE = re.compile(rb"\\u[dD][89a-fA-F]")


def _utf8_text(obj: Any) -> bool:
    """Every string in ``obj`` (keys too) is Unicode text UTF-8 can hold."""
    stack = [obj]
    while stack:
        o = stack.pop()
        if isinstance(o, str):
            try:
                o.encode("utf-8")
            except UnicodeEncodeError:
                return False
        elif isinstance(o, dict):
            stack.extend(o.keys())
            stack.extend(o.values())
        elif isinstance(o, list):
            stack.extend(o)
    return True


def _finite(v: Any, what: str) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise Rejected("bad-value", f"{what} is not a number") from None
    except OverflowError:  # an integer too large for a float
        raise Rejected("non-finite", what) from None
    if not math.isfinite(x):
        raise Rejected("non-finite", what)
    return x


def _integer(v: Any, what: str) -> int:
    x = _finite(v, what)
    if x != int(x):
        raise Rejected("bad-value", f"{what} {v!r} is not an integer")
    return int(x)


def _whole(v: Any, what: str, minimum: int = 0) -> int:
    """A JSON integer >= ``minimum`` (booleans and fractions refused, ``bad-value``; an overflowing
    literal such as 1e999, read as an infinity, ``non-finite``)."""
    if isinstance(v, float) and not math.isfinite(v):
        raise Rejected("non-finite", what)
    if not isinstance(v, int) or isinstance(v, bool) or v < minimum:
        raise Rejected("bad-value", f"{what} must be an integer >= {minimum}, got {v!r}")
    return v


def _finite_list(v: Any, what: str) -> list[float]:
    if not isinstance(v, list):
        raise Rejected("malformed-json", f"{what} must be a list")
    return [_finite(x, what) for x in v]


def _object(v: Any, what: str) -> dict:
    if not isinstance(v, dict):
        raise Rejected("malformed-json", f"{what} must be an object")
    return v


def _text(v: Any, n: int) -> str:
    return "" if v is None else str(v)[:n]


def _floor(v: Any) -> str | None:
    return None if v is None else str(v)


def _matrix2(v: Any, what: str) -> np.ndarray:
    if not (isinstance(v, list) and len(v) == 2 and all(isinstance(r, list) and len(r) == 2 for r in v)):
        raise Rejected("bad-value", f"{what} must be 2x2")
    return np.array([[_finite(x, what) for x in r] for r in v])


def _geojson_multipolygon(area) -> dict:
    """``shapely.geometry.mapping(area)`` of a MultiPolygon (a ContainmentRegion's area) built from its
    rings' coordinate arrays: the same GeoJSON once dumped (arrays for tuples, the same floats), at a
    fraction of the cost of the coordinate-by-coordinate tuples of ``__geo_interface__``."""
    import shapely

    z = bool(area.has_z)
    polys = []
    for p in area.geoms:
        rings = [p.exterior, *p.interiors]
        polys.append([shapely.get_coordinates(r, include_z=z).tolist() for r in rings])
    return {"type": "MultiPolygon", "coordinates": polys}


def _dumps(msg: dict, compact: bool = False) -> bytes:
    if compact:
        return json.dumps(msg, separators=(",", ":"), allow_nan=False).encode("utf-8")
    return json.dumps(msg).encode()


# ---------------------------------------------------------------------------------------------- shared parts
def _id(value: object, what: str) -> str:
    """A site or device id (:func:`~.protocol.check_id`), refused as ``bad-id``."""
    try:
        return check_id(value, what)
    except ValueError as exc:
        raise Rejected("bad-id", str(exc)) from None


def step_to_dict(s: StepEvent) -> dict:
    """A step as the wire writes it (optional fields only when set)."""
    d: dict[str, Any] = {"t": s.t, "length": s.length, "heading": s.heading, "sigma_length": s.sigma_length, "sigma_heading": s.sigma_heading}
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


def step_columns_of(steps) -> dict[str, list]:
    """Steps in the columnar form: a list per field, a step per index; the optional fields' columns only
    when a step sets them, and each value as :func:`step_to_dict` sends it (a ``sigma_heading_change``
    only with a ``heading_change``, a ``sigma_height_change`` only with a non-zero ``height_change``), so
    that both forms decode to the same steps."""
    cols: dict[str, list] = {f: [getattr(s, f) for s in steps] for f in ("t", "length", "heading", "sigma_length", "sigma_heading")}
    hc = [s.heading_change for s in steps]
    if any(x is not None for x in hc):
        cols["heading_change"] = hc
        cols["sigma_heading_change"] = [None if s.heading_change is None else s.sigma_heading_change for s in steps]
    if any(s.height_change for s in steps):
        cols["height_change"] = [s.height_change if s.height_change else 0.0 for s in steps]
        cols["sigma_height_change"] = [s.sigma_height_change if s.height_change else 0.0 for s in steps]
    if any(s.floor_change for s in steps):
        cols["floor_change"] = [s.floor_change for s in steps]
    if any(s.degraded for s in steps):
        cols["degraded"] = [s.degraded for s in steps]
    return cols


def _step_from(s: dict) -> StepEvent:
    """A step as sent; plain well-formed steps (every number a float, in range) take the fast path,
    anything else the checked one, which names the reason. Both give the same steps (tested)."""
    if type(s) is dict:
        t, ln, hd, sl, sh = s.get("t"), s.get("length"), s.get("heading"), s.get("sigma_length"), s.get("sigma_heading")
        hc, shc = s.get("heading_change"), s.get("sigma_heading_change")
        dh, sdh, fc, dg = s.get("height_change", 0.0), s.get("sigma_height_change", 0.0), s.get("floor_change", 0), s.get("degraded", "")
        if (
            type(t) is float and type(ln) is float and type(hd) is float and type(sl) is float and type(sh) is float
            and type(dh) is float and type(sdh) is float
            and (hc is None or type(hc) is float) and (shc is None or type(shc) is float)
            and type(fc) is int and -(2**53) < fc < 2**53 and type(dg) is str and len(dg) <= 32
            # one sum is finite only when every term is (an overflowing sum goes the checked way too)
            and math.isfinite(t + ln + hd + sl + sh + dh + sdh + (hc or 0.0) + (shc or 0.0))
            and ln >= 0.0 and sl >= 0.0 and sh >= 0.0 and sdh >= 0.0
        ):  # fmt: skip
            return StepEvent._checked_already(
                {
                    "t": t, "length": ln, "heading": wrap_angle(hd), "sigma_length": sl, "sigma_heading": sh,
                    "heading_change": None if hc is None else wrap_angle(hc), "sigma_heading_change": shc,
                    "height_change": dh, "sigma_height_change": sdh, "floor_change": fc, "degraded": dg,
                }
            )  # fmt: skip
    return _step_checked(s)


def _step_checked(s: dict) -> StepEvent:
    hc, shc = s.get("heading_change"), s.get("sigma_heading_change")
    return StepEvent(
        _finite(s["t"], "step t"), _finite(s["length"], "length"), _finite(s["heading"], "heading"),
        _finite(s["sigma_length"], "sigma_length"), _finite(s["sigma_heading"], "sigma_heading"),
        None if hc is None else _finite(hc, "heading_change"), None if shc is None else _finite(shc, "sigma_heading_change"),
        _finite(s.get("height_change", 0.0), "height_change"), _finite(s.get("sigma_height_change", 0.0), "sigma_height_change"),
        _integer(s.get("floor_change", 0), "floor_change"), _text(s.get("degraded", ""), 32),
    )  # fmt: skip


def scan_to_dict(s: RfScan) -> dict:
    """A scan as the wire writes it: readings by transmitter id; frequencies and ages only when known."""
    d = {"t": s.t, "tech": s.technology.value, "rssi": dict(s.rssi_dbm)}
    if s.frequency_hz:
        d["freq"] = dict(s.frequency_hz)
    if s.age_s:
        d["age"] = dict(s.age_s)
    return d


def _readings(v: Any, what: str) -> dict[str, float]:
    return {str(k)[:64]: _finite(x, what) for k, x in _object(v or {}, what).items()}


def _fast_readings(rssi: dict) -> dict[str, float] | None:
    """The readings of a scan that is all plain numbers in range, checked as one array (a real WiFi
    scan has hundreds of readings: per-reading checks were most of a batch's decoding); None when any
    reading needs the per-reading path (which names the reason) or is refused."""
    types = set(map(type, rssi.values()))
    if not types <= {float, int}:  # bool and str go the slow way
        return None
    try:
        arr = np.fromiter(rssi.values(), dtype=float, count=len(rssi))
    except OverflowError:  # an integer past a float's range
        return None
    if not rssi_in_range(arr).all():  # NaN and the infinities are out of range too
        return None
    if rssi and max(map(len, rssi)) > 64:  # JSON keys are str; ids are cut at 64 characters
        return None
    return dict(rssi) if types <= {float} else dict(zip(rssi, arr.tolist()))


def _scan_from(s: dict, device_model: str, allow_empty: bool = False) -> RfScan:
    rssi = s["rssi"]
    if not isinstance(rssi, dict) or not (rssi or allow_empty):
        raise Rejected("bad-scan", "rssi must be a non-empty object")
    clean = _fast_readings(rssi)
    if clean is None:  # something to refuse (or a number only the slow path reads): one by one, exact reason
        clean = {}
        for k, v in rssi.items():
            r = _finite(v, "rssi")
            if not rssi_in_range(r):
                raise Rejected("rssi-out-of-range", f"{r} dBm")
            clean[str(k)[:64]] = r
    tech = s.get("tech", "wifi")
    if tech not in ("wifi", "ble", "rfid"):
        raise Rejected("bad-scan", f"technology {tech!r}")
    freq, age = _readings(s.get("freq"), "freq"), _readings(s.get("age"), "age")
    return RfScan(_finite(s["t"], "scan t"), Technology(tech), clean, freq, age, device_model)


def _structure(fn, *args):
    """``fn(*args)``, its missing or mistyped fields turned into ``malformed-json`` and its records'
    own checks (a negative sigma, a covariance not positive definite ...) into ``bad-value``."""
    try:
        return fn(*args)
    except Rejected:
        raise
    except (KeyError, TypeError, AttributeError, IndexError) as exc:
        raise Rejected("malformed-json", f"missing or wrong field {exc}") from None
    except ValueError as exc:
        raise Rejected("bad-value", str(exc)[:120]) from None


# ---------------------------------------------------------------------------------------------- a batch's typed fast path
# A large batch (1,000 steps + 100 scans) spent most of its decoding in per-field Python checks. A plain
# batch - every field of the type the protocol gives it, every value in its limits, times in order -
# is decoded instead by msgspec into typed structs (the types checked in C) and its values checked as
# whole arrays; anything else (a wrong type, a value to refuse or to count, a field only the general
# path reads, such as a number as a device model) makes :func:`_batch_fast` give up, and the general
# path decides, naming the reason. Both give the same batch (tested on generated batches).
class _WireStep(msgspec.Struct):
    t: float
    length: float
    heading: float
    sigma_length: float
    sigma_heading: float
    heading_change: float | None = None
    sigma_heading_change: float | None = None
    height_change: float = 0.0
    sigma_height_change: float = 0.0
    floor_change: int = 0
    degraded: str = ""


class _WireStepColumns(msgspec.Struct, forbid_unknown_fields=True):
    """A batch's steps in the columnar form (a column the general path would read differently, such as
    an unknown one, makes the typed decoding fail: the general path decides)."""

    t: list[float]
    length: list[float]
    heading: list[float]
    sigma_length: list[float]
    sigma_heading: list[float]
    # left out: UNSET (a null column is refused by the general path, so it fails here)
    heading_change: list[float | None] | msgspec.UnsetType = msgspec.UNSET
    sigma_heading_change: list[float | None] | msgspec.UnsetType = msgspec.UNSET
    height_change: list[float] | msgspec.UnsetType = msgspec.UNSET
    sigma_height_change: list[float] | msgspec.UnsetType = msgspec.UNSET
    floor_change: list[int] | msgspec.UnsetType = msgspec.UNSET
    degraded: list[str] | msgspec.UnsetType = msgspec.UNSET


class _WireScan(msgspec.Struct):
    t: float
    rssi: dict[str, float]
    tech: str = "wifi"
    freq: dict[str, float] | None = None
    age: dict[str, float] | None = None


class _WireMark(msgspec.Struct):
    t: float
    x: float
    y: float
    floor: str | None = ""


class _WireBatch(msgspec.Struct):
    schema: str
    site: str
    device: str
    seq: int
    device_model: str | None = ""
    sent_at: float | None = None
    steps: list[_WireStep] | _WireStepColumns | None = None
    scans: list[_WireScan] | None = None
    marks: list[_WireMark] | None = None
    end_of_walk: bool = False


_BATCH_DECODER = msgspec.json.Decoder(_WireBatch)
_COLUMNAR_ENCODER = msgspec.json.Encoder()
_TECHS = {t.value: t for t in Technology}


def _batch_fast(payload, site: str | None, device: str | None) -> Batch | None:
    """The batch in ``payload`` when it is plain (see above), else None (the general path decides)."""
    if not isinstance(payload, (bytes, bytearray, memoryview)) or len(payload) > MAX_BATCH_BYTES:
        return None
    try:
        m = _BATCH_DECODER.decode(payload)
    except (msgspec.DecodeError, RecursionError):  # ValidationError is a DecodeError
        return None
    scans_in, marks_in = m.scans or [], m.marks or []
    cols = _columns_of(m.steps)
    if cols is None:
        return None
    if m.schema != BATCH_SCHEMA or m.seq < 1 or len(cols[0]) + len(scans_in) + len(marks_in) > MAX_BATCH_ITEMS:
        return None
    model = m.device_model or ""
    if len(model) > 64:
        return None
    try:
        b_site, b_device = check_id(m.site, "site"), check_id(m.device, "device")
    except ValueError:
        return None
    if (site is not None and b_site != site) or (device is not None and b_device != device):
        return None
    sent_at = m.sent_at or 0.0
    if not math.isfinite(sent_at):
        return None
    steps = _steps_fast(*cols)
    scans = _scans_fast(scans_in, model)
    marks = _marks_fast(marks_in)
    if steps is None or scans is None or marks is None:
        return None
    times = step_times(steps) + [x.t for x in scans] + [x.t for x in marks]
    if times and not max(times) <= min(times) + limits.MAX_BATCH_SPAN_S:
        return None  # limits.screen would cut the batch to its largest window (the same comparison as limits._largest_window's)
    return Batch(b_site, b_device, m.seq, model, steps, scans, marks, sent_at, m.end_of_walk, ())


def step_times(steps: Sequence[StepEvent]) -> list[float]:
    """The steps' times (read from the column of :class:`~.messages.StepColumns`, without making the steps)."""
    return list(steps.columns[0]) if isinstance(steps, StepColumns) else [x.t for x in steps]


def _non_decreasing(t: np.ndarray) -> bool:
    return bool(t.size < 2 or (np.diff(t) >= 0.0).all())


#: A step's fields in :class:`~hybridloc.types.StepEvent`'s order: the columns of the columnar form
STEP_FIELDS = tuple(f.name for f in dataclasses.fields(StepEvent))
_StepColumns = tuple[list, list, list, list, list, list, list, list, list, list, list]


def _columns_of(steps: list[_WireStep] | _WireStepColumns | None) -> _StepColumns | None:
    """A batch's typed steps, rows or columns, as the 11 columns of :data:`STEP_FIELDS` (absent optional
    ones filled as an absent field reads: None, 0.0, 0, ""); None when the columns differ in length."""
    if steps is None:
        return ([], [], [], [], [], [], [], [], [], [], [])
    if isinstance(steps, list):
        return tuple([getattr(s, f) for s in steps] for f in STEP_FIELDS)  # type: ignore[return-value]
    n = len(steps.t)
    opt = (steps.heading_change, steps.sigma_heading_change, steps.height_change, steps.sigma_height_change, steps.floor_change, steps.degraded)
    if any(len(c) != n for c in (steps.length, steps.heading, steps.sigma_length, steps.sigma_heading)) or any(
        c is not msgspec.UNSET and len(c) != n for c in opt
    ):
        return None
    fill = (None, None, 0.0, 0.0, 0, "")
    return (steps.t, steps.length, steps.heading, steps.sigma_length, steps.sigma_heading) + tuple(  # type: ignore[return-value]
        [f] * n if c is msgspec.UNSET else c for c, f in zip(opt, fill)
    )


def _steps_fast(
    t: list, ln: list, hd: list, sl: list, sh: list, hc: list, shc: list, dh: list, sdh: list, fc: list, dg: list
) -> Sequence[StepEvent] | None:
    """The steps of these columns, when each is within :mod:`.limits` and in time at the rate they allow
    (so that limits.screen would keep every one), values as the general path gives them; else None."""
    if not t:
        return ()
    if len(t) <= _SCALAR_STEPS:
        return _steps_scalar(t, ln, hd, sl, sh, hc, shc, dh, sdh, fc, dg)
    return _steps_numpy(t, ln, hd, sl, sh, hc, shc, dh, sdh, fc, dg)


def _steps_numpy(
    t: list, ln: list, hd: list, sl: list, sh: list, hc: list, shc: list, dh: list, sdh: list, fc: list, dg: list
) -> Sequence[StepEvent] | None:
    """:func:`_steps_fast` on numpy arrays (many steps: a spool replay's 1,000)."""
    A = np.array([t, ln, hd, sl, sh, dh, sdh], float)
    has_hc = [x is not None for x in hc]
    H = np.array([x if x is not None else 0.0 for x in hc], float)
    SH = np.array([x if x is not None else 0.0 for x in shc], float)
    at, aln, ahd, asl, ash, adh, asdh = A
    ok = (
        np.isfinite(A).all()
        and np.isfinite(H).all()
        and np.isfinite(SH).all()
        and (aln >= 0.0).all() and (asl >= 0.0).all() and (ash >= 0.0).all() and (asdh >= 0.0).all() and (SH >= 0.0).all()
        # limits.screen's per-step reasons: units, length, turn, climb
        and (np.abs(at) < limits.MAX_ABS_TIME_S).all()
        and (np.abs(ahd) <= limits.MAX_ANGLE_RAD).all() and (ash <= limits.MAX_ANGLE_RAD).all() and (np.abs(SH) <= limits.MAX_ANGLE_RAD).all()
        and (aln <= limits.MAX_STEP_LENGTH_M).all()
        and (np.abs(H) <= limits.MAX_HEADING_CHANGE_RAD).all()
        and (np.abs(adh) <= limits.MAX_HEIGHT_CHANGE_M).all()
        and -limits.MAX_FLOOR_CHANGE <= min(fc) and max(fc) <= limits.MAX_FLOOR_CHANGE
        and max(map(len, dg)) <= 32
    )  # fmt: skip
    if not ok:
        return None
    # in time order, each step after the previous by at least the shortest step interval and at most the top speed
    dt = np.diff(at)
    if not ((dt >= limits.MIN_STEP_INTERVAL_S).all() and (aln[1:] <= limits.MAX_STEP_SPEED_M_S * dt).all()):
        return None
    heading = wrap_angle(ahd).tolist()  # np.mod: Python's float % bit for bit (units.wrap_angle)
    change = [c if h else None for c, h in zip(wrap_angle(H).tolist(), has_hc)]
    # the columns as Python floats (msgspec gives ints where the JSON had them only for int columns)
    t, ln, sl, sh, dh, sdh = (A[k].tolist() for k in (0, 1, 3, 4, 5, 6))
    # held as columns: the server stores them as such, never making a thousand StepEvents per batch
    return StepColumns([t, ln, heading, sl, sh, change, list(shc), dh, sdh, list(fc), list(dg)])


#: Up to this many steps, :func:`_steps_fast` checks them one by one in Python: a live batch (a phone's
#: second: 2 steps) paid ~25 numpy calls' overhead, most of the server's decoding under bench_load
_SCALAR_STEPS = 16


def _steps_scalar(
    t: list, ln: list, hd: list, sl: list, sh: list, hc: list, shc: list, dh: list, sdh: list, fc: list, dg: list
) -> Sequence[StepEvent] | None:
    """:func:`_steps_fast` for a few steps: the same checks on Python floats (float64, as numpy's), the
    same result (tests/test_wire_codecs.py holds the two to each other)."""
    isfin = math.isfinite
    try:
        T, L, HD, SL, SH_, DH, SDH = ([float(x) for x in c] for c in (t, ln, hd, sl, sh, dh, sdh))
        H = [0.0 if x is None else float(x) for x in hc]
        SHC = [0.0 if x is None else float(x) for x in shc]
    except (TypeError, ValueError, OverflowError):
        return None
    for i in range(len(T)):
        ti, li, hi, sli, shi, dhi, sdhi, ci, sci = T[i], L[i], HD[i], SL[i], SH_[i], DH[i], SDH[i], H[i], SHC[i]
        if not (
            isfin(ti) and isfin(li) and isfin(hi) and isfin(sli) and isfin(shi) and isfin(dhi) and isfin(sdhi) and isfin(ci) and isfin(sci)
            and li >= 0.0 and sli >= 0.0 and shi >= 0.0 and sdhi >= 0.0 and sci >= 0.0
            and abs(ti) < limits.MAX_ABS_TIME_S
            and abs(hi) <= limits.MAX_ANGLE_RAD and shi <= limits.MAX_ANGLE_RAD and abs(sci) <= limits.MAX_ANGLE_RAD
            and li <= limits.MAX_STEP_LENGTH_M
            and abs(ci) <= limits.MAX_HEADING_CHANGE_RAD
            and abs(dhi) <= limits.MAX_HEIGHT_CHANGE_M
        ):  # fmt: skip
            return None
        if i:
            dt = ti - T[i - 1]
            if not (dt >= limits.MIN_STEP_INTERVAL_S and li <= limits.MAX_STEP_SPEED_M_S * dt):
                return None
    if not (-limits.MAX_FLOOR_CHANGE <= min(fc) and max(fc) <= limits.MAX_FLOOR_CHANGE and max(map(len, dg)) <= 32):
        return None
    heading = [wrap_angle(x) for x in HD]
    change = [None if x is None else wrap_angle(c) for x, c in zip(hc, H)]
    return StepColumns([T, L, heading, SL, SH_, change, list(shc), DH, SDH, list(fc), list(dg)])


def _scans_fast(scans_in: list[_WireScan], model: str) -> tuple[RfScan, ...] | None:
    """The scans, when every reading is in range, every id at most 64 characters, no reading too
    old, frequencies in range and times in order; else None."""
    out = []
    vals: list[float] = []
    for s in scans_in:
        if not s.rssi or s.tech not in _TECHS or len(s.rssi) > limits.MAX_SCAN_READINGS:
            return None
        freq, age = s.freq or {}, s.age or {}
        for d in (s.rssi, freq, age):
            if d and max(map(len, d)) > 64:
                return None
        if any(not (limits.MIN_FREQUENCY_HZ <= f <= limits.MAX_FREQUENCY_HZ) for f in freq.values()):
            return None
        if any(not (0.0 <= a <= limits.MAX_READING_AGE_S) for a in age.values()):
            return None
        vals.extend(s.rssi.values())
        out.append(RfScan._checked_already(s.t, _TECHS[s.tech], s.rssi, freq, age, model))
    t = np.array([s.t for s in scans_in], float)
    if not (np.isfinite(t).all() and (np.abs(t) < limits.MAX_ABS_TIME_S).all() and _non_decreasing(t)):
        return None
    if vals and not rssi_in_range(np.array(vals, float)).all():
        return None
    return tuple(out)


def _marks_fast(marks_in: list[_WireMark]) -> tuple[SurveyMark, ...] | None:
    out = []
    for mk in marks_in:
        floor = mk.floor or ""
        if not (math.isfinite(mk.t + mk.x + mk.y) and abs(mk.t) < limits.MAX_ABS_TIME_S and abs(mk.x) <= limits.MAX_ABS_COORD_M):
            return None
        if abs(mk.y) > limits.MAX_ABS_COORD_M or len(floor) > 32:
            return None
        out.append(SurveyMark(mk.t, mk.x, mk.y, floor))
    if not _non_decreasing(np.array([mk.t for mk in out], float)):
        return None
    return tuple(out)


# ---------------------------------------------------------------------------------------------- codecs
class Codec(Generic[R]):
    """``encode(record) -> bytes``, ``decode(bytes) -> record``; ``decode(encode(r))`` equals ``r``."""

    schema: str = ""

    @property
    def encoding(self) -> str:
        """The Zenoh encoding of the payload."""
        return encoding(self.schema)

    def encode(self, record: R) -> bytes:
        raise NotImplementedError

    def decode(self, payload: bytes) -> R:
        raise NotImplementedError


class BatchCodec(Codec[Batch]):
    schema = BATCH_SCHEMA

    def encode(self, b: Batch, step_columns: bool = False) -> bytes:
        """Today's bytes; ``step_columns``: the steps in the columnar form (docs/protocol.md, "Step
        columns"), which servers before it refuse (``malformed-json``): for large batches to a server
        that reads it. Both forms decode to the same batch."""
        msg = {
            "schema": BATCH_SCHEMA, "site": b.site, "device": b.device, "seq": int(b.seq), "device_model": b.device_model, "sent_at": b.sent_at,
            "steps": step_columns_of(b.steps) if step_columns else [step_to_dict(s) for s in b.steps],
            "scans": [scan_to_dict(s) for s in b.scans],
            "marks": [{"t": m.t, "x": m.x, "y": m.y, "floor": m.floor} for m in b.marks],
        }  # fmt: skip
        if b.end_of_walk:  # optional: absent means false, so batches of older clients read the same
            msg["end_of_walk"] = True
        if step_columns:  # a new form, so new bytes: msgspec's (shortest round-trip floats, as json's), several times faster
            return _COLUMNAR_ENCODER.encode(msg)
        return _dumps(msg, compact=True)

    def decode(self, payload: bytes, site: str | None = None, device: str | None = None) -> Batch:
        """The batch in ``payload``; ``site``/``device``: the ids its key names (``key-mismatch`` otherwise)."""
        fast = _batch_fast(payload, site, device)
        return fast if fast is not None else self.decode_general(payload, site, device)

    def decode_general(self, payload: bytes, site: str | None = None, device: str | None = None) -> Batch:
        """:meth:`decode` without the typed fast path: every field read and checked one by one."""
        msg = _load(payload, BATCH_SCHEMA, MAX_BATCH_BYTES)
        b_site, b_device = _id(msg.get("site"), "site"), _id(msg.get("device"), "device")
        if (site is not None and b_site != site) or (device is not None and b_device != device):
            raise Rejected("key-mismatch", f"payload says {b_site}/{b_device}, key says {site}/{device}")
        seq = msg.get("seq")
        if not isinstance(seq, int) or isinstance(seq, bool) or seq < 1:
            raise Rejected("bad-seq", repr(seq))
        steps_in, scans_in, marks_in = _step_rows(msg.get("steps") or []), msg.get("scans") or [], msg.get("marks") or []
        if not all(isinstance(x, list) for x in (steps_in, scans_in, marks_in)):
            raise Rejected("malformed-json", "steps, scans and marks must be lists")
        if len(steps_in) + len(scans_in) + len(marks_in) > MAX_BATCH_ITEMS:
            raise Rejected("too-large", f"more than {MAX_BATCH_ITEMS} items")
        model = _text(msg.get("device_model", ""), 64)

        def items():
            steps = tuple(_step_from(s) for s in steps_in)
            scans = tuple(_scan_from(s, model) for s in scans_in)
            marks = tuple(
                SurveyMark(_finite(m["t"], "mark t"), _finite(m["x"], "x"), _finite(m["y"], "y"), _text(m.get("floor", ""), 32)) for m in marks_in
            )
            return steps, scans, marks

        steps, scans, marks = _structure(items)
        end = msg.get("end_of_walk", False)
        if not isinstance(end, bool):
            raise Rejected("bad-value", f"end_of_walk must be true or false, got {end!r}")
        sent_at = _finite(msg.get("sent_at") or 0.0, "sent_at")
        # items beyond a physical limit are left out one by one and counted; the batch is kept
        sent = [(float(s["heading"]), None if s.get("heading_change") is None else float(s["heading_change"])) for s in steps_in]
        steps, scans, marks, refused = limits.screen(steps, scans, marks, sent)
        return Batch(b_site, b_device, seq, model, steps, scans, marks, sent_at, end, tuple(sorted(refused.items())))


def _step_rows(steps: Any) -> Any:
    """The steps of a batch as rows: the list as sent, or the columnar form's rows (step i holds each
    column's i-th value, under the column's name), so that both forms are read by the same code;
    anything else as it is (the caller refuses it). Columns that are not lists are ``malformed-json``,
    columns of unequal lengths ``bad-value``."""
    if not isinstance(steps, dict):
        return steps
    if not all(isinstance(c, list) for c in steps.values()):
        raise Rejected("malformed-json", "step columns must be lists")
    lengths = {len(c) for c in steps.values()}
    if len(lengths) > 1:
        raise Rejected("bad-value", f"step columns of unequal lengths {sorted(lengths)}")
    names = list(steps)
    return [dict(zip(names, values)) for values in zip(*steps.values())]


class AckCodec(Codec[Ack]):
    schema = ACK_SCHEMA

    def encode(self, a: Ack) -> bytes:
        return _dumps({"schema": ACK_SCHEMA, "device": a.device, "acked_seq": int(a.acked_seq)})

    def decode(self, payload: bytes) -> Ack:
        msg = _load(payload, ACK_SCHEMA)
        device = _id(msg.get("device"), "device")
        seq = msg.get("acked_seq")
        if not isinstance(seq, int) or isinstance(seq, bool) or seq < 0:
            raise Rejected("bad-seq", repr(seq))
        return Ack(device, seq)


class FixCodec(Codec[Fix]):
    schema = FIX_SCHEMA

    def encode(self, a: Fix) -> bytes:
        fix = a.fix
        if fix is None:
            d: dict[str, Any] = {"schema": FIX_SCHEMA, "fix": None, "reason": a.reason}
            if a.t is not None:
                d["t"] = float(a.t)
            return _dumps(d)
        d = {
            "schema": FIX_SCHEMA,
            "fix": {
                "t": fix.t,
                "x": float(fix.pos_enu[0]),
                "y": float(fix.pos_enu[1]),
                "cov": fix.cov[:2, :2].tolist(),
                "floor": fix.floor,
                "floor_prob": fix.floor_prob,
                "source": fix.source.value,
            },
        }
        if a.region is not None:
            d["region"] = {"floor": a.region.floor, "mass": a.region.mass, "geometry": _geojson_multipolygon(a.region.area)}
        if a.floor_probs:
            d["floor_probs"] = dict(a.floor_probs)
        return _dumps(d)

    def decode(self, payload: bytes) -> Fix:
        msg = _load(payload, FIX_SCHEMA)
        f = msg.get("fix")
        if f is None:
            t = msg.get("t")
            return Fix(None, reason=_text(msg.get("reason", ""), 1000), t=None if t is None else _finite(t, "t"))
        return _structure(self._fix, _object(f, "fix"), msg)

    @staticmethod
    def _fix(f: dict, msg: dict) -> Fix:
        t = _finite(f["t"], "fix t")
        fix = AbsoluteFix(
            t,
            np.array([_finite(f["x"], "x"), _finite(f["y"], "y")]),
            _matrix2(f["cov"], "cov"),
            f["source"],
            _floor(f.get("floor")),
            _finite(f.get("floor_prob", 1.0), "floor_prob"),
        )
        region = None
        if msg.get("region") is not None:
            r = _object(msg["region"], "region")
            region = ContainmentRegion(_floor(r.get("floor")), _geometry(r["geometry"]), _finite(r["mass"], "mass"), t)
        probs = {}
        for k, v in _object(msg.get("floor_probs") or {}, "floor_probs").items():
            p = _finite(v, "floor_probs")
            if not 0.0 <= p <= 1.0:
                raise Rejected("bad-value", f"floor probability {p} outside [0, 1]")
            probs[str(k)[:32]] = p
        return Fix(fix, region, probs)


def _geometry(g: Any):
    """A (Multi)Polygon from its GeoJSON mapping."""
    import shapely
    from shapely.geometry import shape

    if not isinstance(g, dict) or g.get("type") not in ("Polygon", "MultiPolygon"):
        raise Rejected("bad-value", "region geometry must be a GeoJSON Polygon or MultiPolygon")
    try:
        area = shape(g)
        coords = shapely.get_coordinates(area)
    except Exception as exc:  # noqa: BLE001 - shapely raises several kinds on bad coordinates
        raise Rejected("bad-value", f"region geometry: {str(exc)[:80]}") from None
    if not np.all(np.isfinite(coords)):
        raise Rejected("non-finite", "region geometry")
    return area


class PoseCodec(Codec[Pose]):
    schema = POSE_SCHEMA

    def encode(self, p: Pose) -> bytes:
        d = {"schema": POSE_SCHEMA, "t": p.t, "x": p.x, "y": p.y, "floor": p.floor}
        if p.cov is not None:
            d["cov"] = p.cov.tolist()
        return _dumps(d)

    def decode(self, payload: bytes) -> Pose:
        msg = _load(payload, POSE_SCHEMA, MAX_MESSAGE_BYTES)

        def pose():
            cov = None
            if msg.get("cov") is not None:
                cov = _matrix2(msg["cov"], "cov")
                if cov[0, 0] < 0 or cov[1, 1] < 0:
                    raise Rejected("bad-value", "cov: negative variance")
            return Pose(_finite(msg["t"], "t"), _finite(msg["x"], "x"), _finite(msg["y"], "y"), _floor(msg.get("floor")), cov)

        return _structure(pose)


class LocateCodec(Codec[LocateRequest]):
    schema = LOCATE_SCHEMA

    def encode(self, q: LocateRequest) -> bytes:
        d = {"schema": LOCATE_SCHEMA, "scan": scan_to_dict(q.scan)}
        if q.scan.device_model:
            d["device_model"] = q.scan.device_model
        return _dumps(d)

    def decode(self, payload: bytes) -> LocateRequest:
        """A scan without readings is taken (its answer is "no fix")."""
        msg = _load(payload, LOCATE_SCHEMA, MAX_MESSAGE_BYTES)
        scan = _structure(_scan_from, _object(msg.get("scan"), "scan"), _text(msg.get("device_model", ""), 64), True)
        kept, refused = limits.screen_scan(scan)
        if kept is None and set(refused) != {"reading-too-old"}:  # the scan itself is beyond a limit
            (reason,) = refused
            raise Rejected(reason, f"the scan: {reason}")
        # stale readings are dropped; a scan left with none is answered "no fix"
        return LocateRequest(kept if kept is not None else RfScan(scan.t, scan.technology, {}, {}, {}, scan.device_model))


class StatusCodec(Codec[Status]):
    schema = STATUS_SCHEMA

    def encode(self, s: Status) -> bytes:
        d = {"schema": STATUS_SCHEMA, "online": list(s.online), "counts": dict(s.counts), "db": dict(s.db), "maps_loaded": dict(s.maps_loaded)}
        if s.slam:  # optional: servers without the crowd SLAM send the bytes they always sent
            d["slam"] = {site: dict(v) for site, v in s.slam.items()}
        if s.sites:  # optional: a process serving every site sends the bytes it always sent
            d["sites"] = list(s.sites)
        if s.rejections:  # optional: a server with nothing refused sends the bytes it always sent
            d["rejections"] = {device: dict(v) for device, v in s.rejections.items()}
        return _dumps(d)

    def decode(self, payload: bytes) -> Status:
        msg = _load(payload, STATUS_SCHEMA)
        online = msg.get("online", [])
        if not (isinstance(online, list) and all(isinstance(d, str) for d in online)):
            raise Rejected("malformed-json", "online must be a list of device ids")
        counts, maps = _object(msg.get("counts", {}), "counts"), _object(msg.get("maps_loaded", {}), "maps_loaded")
        for what, m in (("counts", counts), ("maps_loaded", maps)):
            if not all(isinstance(v, int) and not isinstance(v, bool) for v in m.values()):
                raise Rejected("bad-value", f"{what} must be integers")
        slam = _object(msg.get("slam") or {}, "slam")
        if not all(isinstance(v, dict) for v in slam.values()):
            raise Rejected("malformed-json", "slam must map each site to an object")
        sites = msg.get("sites") or []
        if not isinstance(sites, list):
            raise Rejected("malformed-json", "sites must be a list of site ids")
        rejections = {}
        for device, by_reason in _object(msg.get("rejections") or {}, "rejections").items():
            by_reason = _object(by_reason, "rejections")
            if not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in by_reason.values()):
                raise Rejected("bad-value", "rejections must be counts >= 0")
            rejections[str(device)[:64]] = {str(k)[:64]: n for k, n in by_reason.items()}
        return Status(tuple(online), counts, _object(msg.get("db", {}), "db"), maps, slam, tuple(_id(x, "site") for x in sites), rejections)


class MapInfoCodec(Codec[MapInfo]):
    """The ``map`` reply's attachment (no schema key: ``{"site", "version"}``)."""

    def encode(self, m: MapInfo) -> bytes:
        return _dumps({"site": m.site, "version": int(m.version)})

    def decode(self, payload: bytes) -> MapInfo:
        msg = _load(payload, None)
        site = _id(msg.get("site"), "site")
        v = msg.get("version")
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise Rejected("bad-value", f"map version {v!r}")
        return MapInfo(site, v)


class TrackCodec(Codec[Track]):
    """A corrected track, columnar: one list per field, a point per index.

    ``{"schema", "site", "device", "walk_id", "run", "map_version", "sent_at", "anchored", "scale",
    "heading_bias", "t": [...], "x": [...], "y": [...], "cov": [[xx, xy, yy] or null, ...],
    "floor": [[name, count], ...] (runs of equal floors), "kind": ["step" | "scan", ...]}``.
    """

    schema = TRACK_SCHEMA

    def encode(self, m: Track) -> bytes:
        """The track's newest MAX_TRACK_POINTS points (fewer if even those would pass MAX_TRACK_BYTES)."""
        keep = min(len(m.track), MAX_TRACK_POINTS)
        while True:
            payload = _dumps(self._message(m, len(m.track) - keep), compact=True)
            if len(payload) <= MAX_TRACK_BYTES or keep == 0:
                return payload
            keep //= 2

    @staticmethod
    def _message(m: Track, start: int) -> dict:
        tr = m.track
        cov = np.asarray(tr.cov[start:], float)
        ok = np.isfinite(cov).all(axis=(1, 2))
        tri = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]], axis=1).tolist() if len(cov) else []
        runs: list[list] = []
        for f in tr.floor[start:]:
            f = f[:32]
            if runs and runs[-1][0] == f:
                runs[-1][1] += 1
            else:
                runs.append([f, 1])
        return {
            "schema": TRACK_SCHEMA, "site": m.site, "device": m.device, "walk_id": int(m.walk_id), "run": int(m.run),
            "map_version": None if m.map_version is None else int(m.map_version), "sent_at": float(m.sent_at),
            "anchored": tr.anchored, "scale": float(tr.scale), "heading_bias": float(tr.heading_bias),
            "t": tr.t[start:].tolist(), "x": tr.pos_enu[start:, 0].tolist(), "y": tr.pos_enu[start:, 1].tolist(),
            "cov": [c if good else None for c, good in zip(tri, ok.tolist())],
            "floor": runs, "kind": list(tr.kind[start:]),
        }  # fmt: skip

    def decode(self, payload: bytes, site: str | None = None, device: str | None = None) -> Track:
        """The track in ``payload``; ``site``/``device``: the ids its key names (``key-mismatch`` otherwise)."""
        msg = _load(payload, TRACK_SCHEMA, MAX_TRACK_BYTES)
        m_site, m_device = _id(msg.get("site"), "site"), _id(msg.get("device"), "device")
        if (site is not None and m_site != site) or (device is not None and m_device != device):
            raise Rejected("key-mismatch", f"payload says {m_site}/{m_device}, key says {site}/{device}")
        walk_id, run = _whole(msg.get("walk_id"), "walk_id", 1), _whole(msg.get("run"), "run", 1)
        mv = msg.get("map_version")
        map_version = None if mv is None else _whole(mv, "map_version", 1)
        t = _finite_list(msg.get("t"), "t")
        n = len(t)
        if n > MAX_TRACK_POINTS:
            raise Rejected("too-large", f"{n} points > {MAX_TRACK_POINTS}")
        x, y = _finite_list(msg.get("x"), "x"), _finite_list(msg.get("y"), "y")
        cov_in, kind, runs = msg.get("cov"), msg.get("kind"), msg.get("floor")
        if not (isinstance(cov_in, list) and isinstance(kind, list) and isinstance(runs, list)):
            raise Rejected("malformed-json", "cov, floor and kind must be lists")
        cov = np.full((n, 2, 2), np.nan)
        if len(x) != n or len(y) != n or len(cov_in) != n or len(kind) != n:
            raise Rejected("bad-value", f"{n} times but {len(x)} x, {len(y)} y, {len(cov_in)} covariances, {len(kind)} kinds")
        for i, c in enumerate(cov_in):
            if c is not None:
                cov[i] = _psd2(c)
        if any(b < a for a, b in zip(t, t[1:])):
            raise Rejected("bad-value", "times must not decrease")
        if not all(k in ("step", "scan") for k in kind):
            raise Rejected("bad-value", "a kind is not 'step' or 'scan'")
        floor: list[str] = []
        for r in runs:
            if not (isinstance(r, list) and len(r) == 2 and isinstance(r[0], str)):
                raise Rejected("malformed-json", "a floor run must be [name, count]")
            count = _whole(r[1], "floor count", 1)
            if len(floor) + count > n:  # checked before the list grows: a count of 10**12 is refused, not allocated
                raise Rejected("bad-value", f"floor runs cover more than {n} points")
            floor += [r[0][:32]] * count
        if len(floor) != n:
            raise Rejected("bad-value", f"floor runs cover {len(floor)} points, not {n}")
        anchored = msg.get("anchored")
        if anchored not in TRACK_ANCHORS:
            raise Rejected("bad-value", f"anchored {anchored!r} is not one of {TRACK_ANCHORS}")
        scale, bias = _finite(msg.get("scale"), "scale"), _finite(msg.get("heading_bias"), "heading_bias")
        if scale <= 0:
            raise Rejected("bad-value", f"scale {scale} must be positive")
        sent = msg.get("sent_at")
        sent_at = _finite(0.0 if sent is None else sent, "sent_at")
        pos = np.column_stack([x, y]) if n else np.zeros((0, 2))

        def record() -> Track:
            track = CorrectedTrack(walk_id, np.array(t, float), pos, cov, tuple(floor), tuple(kind), anchored, scale, bias)
            return Track(m_site, m_device, walk_id, map_version, run, track, sent_at)

        return _structure(record)


def _psd2(c: Any) -> np.ndarray:
    """A 2x2 covariance from its upper triangle [xx, xy, yy], positive semi-definite (``bad-value``)."""
    if not (isinstance(c, list) and len(c) == 3):
        raise Rejected("bad-value", "a covariance must be [xx, xy, yy] or null")
    xx, xy, yy = (_finite(v, "cov") for v in c)
    # PSD: both variances >= 0 and the determinant >= 0 (xy^2 <= xx yy), a relative 1e-9 allowed for
    # a marginal covariance rounded by the solver
    if xx < 0 or yy < 0 or xy * xy > xx * yy * (1.0 + 1e-9):
        raise Rejected("bad-value", f"covariance [{xx}, {xy}, {yy}] is not positive semi-definite")
    return np.array([[xx, xy], [xy, yy]])


class MapVersionCodec(Codec[MapVersion]):
    schema = MAP_VERSION_SCHEMA

    def encode(self, m: MapVersion) -> bytes:
        return _dumps(
            {
                "schema": MAP_VERSION_SCHEMA, "site": m.site, "version": int(m.version), "source": m.source, "created_at": float(m.created_at),
                "walks": int(m.walks), "coverage": None if m.coverage is None else float(m.coverage),
            }
        )  # fmt: skip

    def decode(self, payload: bytes) -> MapVersion:
        msg = _load(payload, MAP_VERSION_SCHEMA, MAX_MESSAGE_BYTES)
        site = _id(msg.get("site"), "site")
        version, walks = _whole(msg.get("version"), "version", 1), _whole(msg.get("walks", 0), "walks")
        source = msg.get("source")
        if source not in MAP_SOURCES:
            raise Rejected("bad-value", f"source {source!r} is not one of {MAP_SOURCES}")
        cov = msg.get("coverage")
        coverage = None if cov is None else _finite(cov, "coverage")
        if coverage is not None and not 0.0 <= coverage <= 1.0:
            raise Rejected("bad-value", f"coverage {coverage} outside [0, 1]")
        return MapVersion(site, version, source, _finite(msg.get("created_at"), "created_at"), walks, coverage)


class ProgressCodec(Codec[Progress]):
    schema = PROGRESS_SCHEMA

    def encode(self, p: Progress) -> bytes:
        return _dumps(
            {
                "schema": PROGRESS_SCHEMA,
                "site": p.site,
                "stage": p.stage,
                "floor": p.floor,
                "done": int(p.done),
                "total": int(p.total),
                "t": float(p.t),
            }
        )

    def decode(self, payload: bytes) -> Progress:
        msg = _load(payload, PROGRESS_SCHEMA, MAX_MESSAGE_BYTES)
        site = _id(msg.get("site"), "site")
        stage, floor = msg.get("stage"), msg.get("floor", "")
        if not (isinstance(stage, str) and isinstance(floor, str)):
            raise Rejected("malformed-json", "stage and floor must be texts")
        if not stage:
            raise Rejected("bad-value", "stage is empty")
        done, total = _whole(msg.get("done"), "done"), _whole(msg.get("total"), "total")
        if done > total:
            raise Rejected("bad-value", f"done {done} > total {total}")
        return Progress(site, stage[:32], floor[:32], done, total, _finite(msg.get("t"), "t"))


BATCH = BatchCodec()
ACK = AckCodec()
FIX = FixCodec()
POSE = PoseCodec()
LOCATE = LocateCodec()
STATUS = StatusCodec()
MAP_INFO = MapInfoCodec()
TRACK = TrackCodec()
MAP_VERSION = MapVersionCodec()
PROGRESS = ProgressCodec()
#: Every codec, by message name.
CODECS: Mapping[str, Codec] = {
    "batch": BATCH,
    "ack": ACK,
    "fix": FIX,
    "pose": POSE,
    "locate": LOCATE,
    "status": STATUS,
    "map-info": MAP_INFO,
    "track": TRACK,
    "map-version": MAP_VERSION,
    "progress": PROGRESS,
}
