"""The wire codecs: round trips of every message (hypothesis), every rejection reason named by the
decoder, nothing but ``Rejected`` escaping a decoder, and today's bytes (golden) so the wire cannot drift."""

import dataclasses
import json
import math
import re
import warnings

import numpy as np
import pytest
import shapely
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from hybridloc.types import (
    RSSI_MAX_DBM,
    RSSI_MIN_DBM,
    TRACK_ANCHORS,
    AbsoluteFix,
    ContainmentRegion,
    CorrectedTrack,
    Fix,
    FixSource,
    Pose,
    RfScan,
    StepEvent,
    SurveyMark,
    Technology,
)
from hybridloc.wire import codecs as C
from hybridloc.wire import limits as L
from hybridloc.wire import protocol as P
from hybridloc.wire.messages import MAP_SOURCES, Ack, Batch, LocateRequest, MapInfo, MapVersion, Progress, Status, StepColumns, Track

# derandomize: a fixed sequence of examples (seeded), the same on every run and machine; no example database in the tree
SETTINGS = settings(derandomize=True, deadline=None, max_examples=60, database=None, suppress_health_check=[HealthCheck.too_slow])

#: Reasons a decoder may give (docs/protocol.md; duplicate, out-of-order, bad-key and bad-locate are the server's).
REASONS = {
    "malformed-json",
    "schema-version",
    "too-large",
    "non-finite",
    "bad-value",
    "bad-id",
    "bad-seq",
    "bad-scan",
    "rssi-out-of-range",
    "key-mismatch",
    *L.REASONS,  # a locate's scan beyond a physical limit
}

# ---------------------------------------------------------------------------------------------- strategies
ids = st.from_regex(r"[A-Za-z0-9_.\-]{1,64}", fullmatch=True)
finite = st.floats(allow_nan=False, allow_infinity=False)
coord = st.floats(-1e6, 1e6, allow_nan=False)
nonneg = st.floats(0.0, 1e3, allow_nan=False)
prob = st.floats(0.0, 1.0, allow_nan=False)
rssi = st.floats(RSSI_MIN_DBM, RSSI_MAX_DBM, allow_nan=False)
tx = st.text(min_size=1, max_size=64)
floor_names = st.text(max_size=32)


@st.composite
def steps(draw):
    hc = draw(st.none() | st.floats(-10.0, 10.0))
    height = draw(st.floats(-5.0, 5.0))
    return StepEvent(
        draw(finite),
        draw(nonneg),
        draw(st.floats(-10.0, 10.0)),
        draw(nonneg),
        draw(nonneg),
        hc,
        None if hc is None else draw(st.none() | nonneg),
        # the wire sends a sigma only with its value (docs/protocol.md)
        height,
        draw(nonneg) if height else 0.0,
        draw(st.integers(-5, 5)),
        draw(st.text(max_size=32)),
    )


@st.composite
def scans(draw, device_model=None, min_readings=1, wild=False):
    """A scan; ``wild``: times, frequencies and ages beyond the physical limits too."""
    keys = draw(st.lists(tx, min_size=min_readings, max_size=6, unique=True))
    some = st.lists(st.sampled_from(keys), unique=True) if keys else st.just([])
    return RfScan(
        draw(finite if wild else st.floats(-1e10, 1e10)),
        draw(st.sampled_from(list(Technology))),
        {k: draw(rssi) for k in keys},
        {k: draw(st.floats(1.0, 1e12) if wild else st.floats(1e8, 1e10)) for k in draw(some)},
        {k: draw(finite if wild else st.floats(0.0, L.MAX_READING_AGE_S)) for k in draw(some)},
        draw(st.text(max_size=64)) if device_model is None else device_model,
    )


marks = st.builds(SurveyMark, finite, finite, finite, floor_names)


@st.composite
def wild_batches(draw):
    """Any batch the records allow, physical limits or not (:mod:`hybridloc.wire.limits`)."""
    model = draw(st.text(max_size=64))
    return Batch(
        draw(ids),
        draw(ids),
        draw(st.integers(1, 2**62)),
        model,
        draw(st.lists(steps(), max_size=4)),
        draw(st.lists(scans(model, wild=True), max_size=4)),
        draw(st.lists(marks, max_size=3)),
        draw(finite),
    )


@st.composite
def batches(draw):
    """A batch within the physical limits (what a client sends): times in order inside a few minutes,
    walker-sized steps, ages and frequencies in range; it round-trips whole."""
    model = draw(st.text(max_size=64))
    t0 = draw(st.floats(-1e10, 1e10))
    dts = draw(st.lists(st.floats(1.01 * L.MIN_STEP_INTERVAL_S, 2.0), max_size=4))  # above the limit after rounding
    st_list = []
    t = t0
    for dt in dts:
        t += dt
        hc = draw(st.none() | st.floats(-6.0, 6.0))
        height = draw(st.floats(-L.MAX_HEIGHT_CHANGE_M, L.MAX_HEIGHT_CHANGE_M))
        length = draw(st.floats(0.0, min(L.MAX_STEP_LENGTH_M, 0.99 * L.MAX_STEP_SPEED_M_S * dt)))
        angle = st.floats(0.0, 6.0)
        st_list.append(
            StepEvent(
                t, length, draw(st.floats(-6.0, 6.0)), draw(st.floats(0.0, 1e3)), draw(angle), hc, None if hc is None else draw(st.none() | angle),
                height, draw(nonneg) if height else 0.0, draw(st.integers(-5, 5)), draw(st.text(max_size=32)),
            )
        )  # fmt: skip
    times = sorted(draw(st.lists(st.floats(t0, t0 + 60.0), max_size=7)))
    sc_list = []
    for ts in times[:4]:
        keys = draw(st.lists(tx, min_size=1, max_size=6, unique=True))
        some = st.lists(st.sampled_from(keys), unique=True)
        sc_list.append(
            RfScan(
                ts, draw(st.sampled_from(list(Technology))), {k: draw(rssi) for k in keys},
                {k: draw(st.floats(1e8, 1e10)) for k in draw(some)}, {k: draw(st.floats(0.0, L.MAX_READING_AGE_S)) for k in draw(some)}, model,
            )
        )  # fmt: skip
    xy = st.floats(-L.MAX_ABS_COORD_M, L.MAX_ABS_COORD_M)
    mk_list = [SurveyMark(ts, draw(xy), draw(xy), draw(floor_names)) for ts in times[4:]]
    return Batch(draw(ids), draw(ids), draw(st.integers(1, 2**62)), model, st_list, sc_list, mk_list, draw(finite))


@st.composite
def covariances(draw):
    """2x2 symmetric positive definite: variances a, b and a correlation |r| <= 0.9."""
    a, b, r = draw(st.floats(1e-2, 1e4)), draw(st.floats(1e-2, 1e4)), draw(st.floats(-0.9, 0.9))
    c = r * math.sqrt(a * b)
    return np.array([[a, c], [c, b]])


@st.composite
def regions(draw, t):
    boxes = [
        shapely.box(x, y, x + w, y + h)
        for x, y, w, h in draw(st.lists(st.tuples(coord, coord, st.floats(0.5, 50), st.floats(0.5, 50)), min_size=1, max_size=3))
    ]
    return ContainmentRegion(draw(st.none() | floor_names), shapely.union_all(boxes), draw(st.floats(0.01, 1.0)), t)


@st.composite
def fixes(draw):
    if draw(st.booleans()):
        return Fix(None, reason=draw(st.text(max_size=100)), t=draw(st.none() | finite))
    t = draw(finite)
    fix = AbsoluteFix(
        t, [draw(coord), draw(coord)], draw(covariances()), draw(st.sampled_from(list(FixSource))), draw(st.none() | floor_names), draw(prob)
    )
    return Fix(fix, draw(st.none() | regions(t)), draw(st.dictionaries(floor_names, prob, max_size=4)))


@st.composite
def poses(draw):
    cov = draw(st.none() | st.tuples(nonneg, finite, finite, nonneg).map(lambda v: np.array([[v[0], v[1]], [v[2], v[3]]])))
    return Pose(draw(finite), draw(finite), draw(finite), draw(st.none() | floor_names), cov)


locates = st.builds(LocateRequest, scans(min_readings=0))
acks = st.builds(Ack, ids, st.integers(0, 2**62))
db_values = st.integers(0, 10**9) | st.dictionaries(st.text(max_size=16), st.integers(0, 10**9), max_size=4)
slam_values = st.none() | st.integers(0, 10**9) | st.floats(0.0, 1.0) | st.text(max_size=8)
statuses = st.builds(
    Status,
    st.lists(ids, max_size=5).map(lambda v: tuple(sorted(v))),
    st.dictionaries(st.text(max_size=32), st.integers(0, 10**9), max_size=6),
    st.dictionaries(st.text(max_size=16), db_values, max_size=6),
    st.dictionaries(ids, st.integers(1, 10**6), max_size=4),
    st.dictionaries(ids, st.dictionaries(st.text(max_size=20), slam_values, max_size=5), max_size=3),
    st.lists(ids, max_size=3, unique=True).map(tuple),
    st.dictionaries(ids, st.dictionaries(st.text(max_size=20), st.integers(0, 10**9), min_size=1, max_size=4), max_size=3),
)
map_infos = st.builds(MapInfo, ids, st.integers(1, 10**9))


@st.composite
def corrected_tracks(draw, walk_id):
    n = draw(st.integers(0, 8))
    t = sorted(draw(st.lists(finite, min_size=n, max_size=n)))
    pos = draw(st.lists(st.tuples(coord, coord), min_size=n, max_size=n))
    # a covariance, or none (all NaN: what the wire's null reads as)
    cov = [draw(st.just(np.full((2, 2), np.nan)) | covariances()) for _ in range(n)]
    few_floors = draw(st.lists(floor_names, min_size=1, max_size=3))  # repeated names make runs
    floor = tuple(draw(st.sampled_from(few_floors)) for _ in range(n))
    kind = tuple(draw(st.sampled_from(["step", "scan"])) for _ in range(n))
    return CorrectedTrack(
        walk_id,
        np.array(t, float),
        np.array(pos, float).reshape(n, 2),
        np.array(cov, float).reshape(n, 2, 2),
        floor,
        kind,
        draw(st.sampled_from(TRACK_ANCHORS)),
        draw(st.floats(1e-3, 1e3)),
        draw(st.floats(-10.0, 10.0)),
    )


@st.composite
def tracks(draw):
    walk_id = draw(st.integers(1, 2**62))
    mv = draw(st.none() | st.integers(1, 10**9))
    return Track(draw(ids), draw(ids), walk_id, mv, draw(st.integers(1, 2**62)), draw(corrected_tracks(walk_id)), draw(finite))


map_versions = st.builds(MapVersion, ids, st.integers(1, 10**9), st.sampled_from(MAP_SOURCES), finite, st.integers(0, 10**9), st.none() | prob)


@st.composite
def progresses(draw):
    total = draw(st.integers(0, 10**9))
    return Progress(draw(ids), draw(st.text(min_size=1, max_size=32)), draw(floor_names), draw(st.integers(0, total)), total, draw(finite))


MESSAGES = {
    "batch": batches(),
    "ack": acks,
    "fix": fixes(),
    "pose": poses(),
    "locate": locates,
    "status": statuses,
    "map-info": map_infos,
    "track": tracks(),
    "map-version": map_versions,
    "progress": progresses(),
}


# ---------------------------------------------------------------------------------------------- equality
ULP_PI = math.ulp(math.pi)


def _same(a, b, where="record"):
    """Field by field: numbers and texts exactly, arrays and mappings by value, geometries exactly.

    One exception: a step's heading is wrapped to (-pi, pi] again by the decoded StepEvent, and
    (h + pi) mod 2 pi - pi can move an already wrapped h by up to an ulp of 2 pi (one rounding in the
    sum, Sterbenz-exact difference)."""
    if isinstance(a, StepEvent) and isinstance(b, StepEvent):
        for name in a.__dataclass_fields__:
            x, y = getattr(a, name), getattr(b, name)
            if name in ("heading", "heading_change") and x is not None and y is not None:
                assert abs(x - y) <= 2 * ULP_PI, (where, name, x, y)
            else:
                _same(x, y, f"{where}.{name}")
        return
    if hasattr(a, "__dataclass_fields__"):
        assert type(a) is type(b), (where, type(a), type(b))
        for name in a.__dataclass_fields__:
            _same(getattr(a, name), getattr(b, name), f"{where}.{name}")
    elif isinstance(a, shapely.Geometry):
        assert shapely.equals_exact(a, b, tolerance=0.0), where
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        # NaN equals NaN here: a track's missing covariance is NaN on both sides
        assert a is not None and b is not None and np.array_equal(np.asarray(a, float), np.asarray(b, float), equal_nan=True), (where, a, b)
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b), (where, a, b)
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        assert math.isnan(b), where
    else:
        assert a == b or (hasattr(a, "keys") and dict(a) == dict(b)), (where, a, b)


# ---------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("name", sorted(MESSAGES))
def test_every_message_round_trips(name):
    codec = C.CODECS[name]

    @SETTINGS
    @given(MESSAGES[name])
    def check(record):
        payload = codec.encode(record)
        assert isinstance(payload, bytes)
        back = codec.decode(payload)
        _same(record, back)
        again = codec.encode(back)
        assert again == payload or name == "batch"  # a step heading may move by an ulp (see _same)
        _same(back, codec.decode(again))

    check()


def test_every_message_has_a_codec():
    assert set(C.CODECS) == set(MESSAGES)
    for name, codec in C.CODECS.items():
        if name != "map-info":  # an attachment, not a payload with a schema
            assert codec.encoding == f"application/json;schema={codec.schema}"


# ---------------------------------------------------------------------------------------------- golden bytes
GOLDEN_BATCH = (
    b'{"schema":"hybridloc.batch/1","site":"site1","device":"dev01","seq":17,"device_model":"OPPO PBCM10","sent_at":1700000000.0,'
    b'"steps":[{"t":1700000000.5,"length":0.71,"heading":1.5700000000000003,"sigma_length":0.06,"sigma_heading":0.2,'
    b'"heading_change":0.009999999999999787,"sigma_heading_change":0.02},{"t":1700000001.0,"length":0.65,"heading":-3.0,"sigma_length":0.05,'
    b'"sigma_heading":0.25,"height_change":0.3,"sigma_height_change":0.05,"floor_change":1,"degraded":"mag-disturbed"}],'
    b'"scans":[{"t":1700000001.0,"tech":"wifi","rssi":{"aa:bb:cc:dd:ee:ff":-61.0,"11:22:33:44:55:66":-80.5},"freq":{"aa:bb:cc:dd:ee:ff":2412000000.0},'
    b'"age":{"aa:bb:cc:dd:ee:ff":1.2}},{"t":1700000001.5,"tech":"ble","rssi":{"uuid_1_2_mac":-70.0}}],'
    b'"marks":[{"t":1700000002.0,"x":12.5,"y":40.0,"floor":"F1"}]}'
)


def _golden_batch() -> Batch:
    steps = [
        StepEvent(1700000000.5, 0.71, 1.57, 0.06, 0.2, 0.01, 0.02),
        StepEvent(1700000001.0, 0.65, -3.0, 0.05, 0.25, None, None, 0.3, 0.05, 1, "mag-disturbed"),
    ]
    scans = [
        RfScan(
            1700000001.0,
            "wifi",
            {"aa:bb:cc:dd:ee:ff": -61.0, "11:22:33:44:55:66": -80.5},
            {"aa:bb:cc:dd:ee:ff": 2412000000.0},
            {"aa:bb:cc:dd:ee:ff": 1.2},
        ),
        RfScan(1700000001.5, "ble", {"uuid_1_2_mac": -70.0}),
    ]
    return Batch("site1", "dev01", 17, "OPPO PBCM10", steps, scans, [SurveyMark(1700000002.0, 12.5, 40.0, "F1")], 1700000000.0)


def _golden_fix() -> AbsoluteFix:
    return AbsoluteFix(1700000001.0, [12.25, 40.5], [[4.0, 0.5], [0.5, 9.0]], "wifi", "F1", 0.875)


def _golden_track() -> Track:
    tr = CorrectedTrack(
        None,
        [1700000000.5, 1700000001.0, 1700000001.0],
        [[12.5, 40.0], [13.25, 40.0], [13.25, 40.5]],
        [[[0.04, 0.01], [0.01, 0.09]], np.full((2, 2), np.nan), [[0.25, 0.0], [0.0, 0.25]]],
        ("F1", "F1", "F2"),
        ("step", "step", "scan"),
        "map",
        1.05,
        -0.02,
    )
    return Track("site1", "dev01", 42, 3, 7, tr, 1700000002.0)


GOLDEN_TRACK = (
    b'{"schema":"hybridloc.track/1","site":"site1","device":"dev01","walk_id":42,"run":7,"map_version":3,"sent_at":1700000002.0,'
    b'"anchored":"map","scale":1.05,"heading_bias":-0.02,"t":[1700000000.5,1700000001.0,1700000001.0],"x":[12.5,13.25,13.25],"y":[40.0,40.0,40.5],'
    b'"cov":[[0.04,0.01,0.09],null,[0.25,0.0,0.25]],"floor":[["F1",2],["F2",1]],"kind":["step","step","scan"]}'
)
FIX_PART = b'"fix": {"t": 1700000001.0, "x": 12.25, "y": 40.5, "cov": [[4.0, 0.5], [0.5, 9.0]], "floor": "F1", "floor_prob": 0.875, "source": "wifi"}'
GOLDEN = [  # (record, the bytes hybridloc sent before the codecs, and sends now)
    ("batch", _golden_batch, GOLDEN_BATCH),
    ("ack", lambda: Ack("dev01", 17), b'{"schema": "hybridloc.ack/1", "device": "dev01", "acked_seq": 17}'),
    (
        "fix",
        lambda: Fix(_golden_fix(), ContainmentRegion("F1", shapely.Polygon([(10, 38), (15, 38), (15, 43), (10, 43)]), 0.95, 1700000001.0)),
        b'{"schema": "hybridloc.fix/1", '
        + FIX_PART
        + b', "region": {"floor": "F1", "mass": 0.95, "geometry": {"type": "MultiPolygon", "coordinates": '
        b"[[[[10.0, 38.0], [15.0, 38.0], [15.0, 43.0], [10.0, 43.0], [10.0, 38.0]]]]}}}",
    ),
    ("fix", lambda: Fix(_golden_fix()), b'{"schema": "hybridloc.fix/1", ' + FIX_PART + b"}"),
    (
        "fix",
        lambda: Fix(None, reason="no known transmitter in the scan", t=1700000001.0),
        b'{"schema": "hybridloc.fix/1", "fix": null, "reason": "no known transmitter in the scan", "t": 1700000001.0}',
    ),
    (
        "fix",
        lambda: Fix(None, reason="no radio map for site 'x'"),
        b'{"schema": "hybridloc.fix/1", "fix": null, "reason": "no radio map for site \'x\'"}',
    ),
    ("pose", lambda: Pose(1.5, 2.0, -3.25, "F1"), b'{"schema": "hybridloc.pose/1", "t": 1.5, "x": 2.0, "y": -3.25, "floor": "F1"}'),
    (
        "locate",
        lambda: LocateRequest(RfScan(1.0, "wifi", {"a1": -50.5})),
        b'{"schema": "hybridloc.locate/1", "scan": {"t": 1.0, "tech": "wifi", "rssi": {"a1": -50.5}}}',
    ),
    (
        "status",
        lambda: Status(("dev01",), {"batches-received": 3}, {"devices": 1}, {"site1": 2}),
        b'{"schema": "hybridloc.status/1", "online": ["dev01"], "counts": {"batches-received": 3}, "db": {"devices": 1}, "maps_loaded": {"site1": 2}}',
    ),
    ("map-info", lambda: MapInfo("site1", 2), b'{"site": "site1", "version": 2}'),
    (
        "status",
        lambda: Status(("dev01",), {}, {}, {"site1": 4}, {"site1": {"walks_corrected": 3, "coverage": 0.5, "map_version": 4}}),
        b'{"schema": "hybridloc.status/1", "online": ["dev01"], "counts": {}, "db": {}, "maps_loaded": {"site1": 4}, '
        b'"slam": {"site1": {"walks_corrected": 3, "coverage": 0.5, "map_version": 4}}}',
    ),
    ("track", lambda: _golden_track(), GOLDEN_TRACK),
    (
        "map-version",
        lambda: MapVersion("site1", 4, "slam", 1700000000.0, 12, 0.75),
        b'{"schema": "hybridloc.map-version/1", "site": "site1", "version": 4, "source": "slam", "created_at": 1700000000.0, "walks": 12, "coverage": 0.75}',
    ),
    (
        "progress",
        lambda: Progress("site1", "solve", "F1", 3, 7, 1700000000.0),
        b'{"schema": "hybridloc.progress/1", "site": "site1", "stage": "solve", "floor": "F1", "done": 3, "total": 7, "t": 1700000000.0}',
    ),
]


@pytest.mark.parametrize("name,record,golden", GOLDEN, ids=[f"{g[0]}-{i}" for i, g in enumerate(GOLDEN)])
def test_bytes_are_todays(name, record, golden):
    """The bytes hybridloc sent before the codecs (same keys, order and separators): old clients and
    spooled batches keep working. Added keys (a pose's cov, a fix's floor_probs) appear only when set."""
    codec = C.CODECS[name]
    assert codec.encode(record()) == golden
    assert codec.encode(codec.decode(golden)) == golden


def test_added_keys_come_last():
    pose = C.POSE.encode(Pose(1.5, 2.0, -3.25, "F1", [[1.0, 0.25], [0.25, 4.0]]))
    assert pose == b'{"schema": "hybridloc.pose/1", "t": 1.5, "x": 2.0, "y": -3.25, "floor": "F1", "cov": [[1.0, 0.25], [0.25, 4.0]]}'
    fix = C.FIX.encode(Fix(_golden_fix(), None, {"F1": 0.875, "F2": 0.125}))
    assert fix == b'{"schema": "hybridloc.fix/1", ' + FIX_PART + b', "floor_probs": {"F1": 0.875, "F2": 0.125}}'
    # an old pose (no cov) still decodes
    assert C.POSE.decode(b'{"schema": "hybridloc.pose/1", "t": 1.5, "x": 2.0, "y": -3.25, "floor": null}').cov is None


def test_deprecated_protocol_names_still_work():
    b = _golden_batch()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert P.encode_batch(b.site, b.device, b.seq, b.steps, b.scans, b.marks, b.device_model, b.sent_at) == GOLDEN_BATCH
        assert P.decode_batch(GOLDEN_BATCH, "site1", "dev01").seq == 17
        assert P.decode_ack(P.encode_ack("dev01", 4)) == 4
        assert P.ScanRecord is RfScan and P.MarkRecord is SurveyMark
        fix, region, reason = P.fix_from_dict(P.fix_to_dict(None, reason="why", t=2.0))
        assert fix is None and region is None and reason == "why"
    assert len(caught) >= 6 and all(issubclass(w.category, DeprecationWarning) for w in caught)
    with pytest.raises(AttributeError):
        P.NoSuchName  # noqa: B018


# ---------------------------------------------------------------------------------------------- rejections
def _reason(codec, payload, **kw) -> str:
    with pytest.raises(P.Rejected) as exc:
        codec.decode(payload, **kw)
    assert exc.value.reason in REASONS
    return exc.value.reason


def _msg(name) -> dict:
    return json.loads(C.CODECS[name].encode(dict(GOLDEN_RECORDS)[name]()))


GOLDEN_RECORDS = [
    ("batch", _golden_batch),
    ("ack", lambda: Ack("dev01", 17)),
    ("fix", lambda: Fix(_golden_fix(), ContainmentRegion("F1", shapely.box(10, 38, 15, 43), 0.95, 1700000001.0), {"F1": 1.0})),
    ("pose", lambda: Pose(1.5, 2.0, -3.25, "F1", [[1.0, 0.0], [0.0, 1.0]])),
    ("locate", lambda: LocateRequest(RfScan(1.0, "wifi", {"a1": -50.5}, {"a1": 2.4e9}, {"a1": 0.5}, "pixel"))),
    ("status", lambda: Status(("dev01",), {"batches-received": 3}, {"devices": 1}, {"site1": 2})),
    ("map-info", lambda: MapInfo("site1", 2)),
    ("track", _golden_track),
    ("map-version", lambda: MapVersion("site1", 4, "slam", 1700000000.0, 12, 0.75)),
    ("progress", lambda: Progress("site1", "solve", "F1", 3, 7, 1700000000.0)),
]


def _dumps(msg) -> bytes:
    return json.dumps(msg).encode()


@pytest.mark.parametrize("name", sorted(MESSAGES))
def test_common_rejections(name):
    codec = C.CODECS[name]
    assert _reason(codec, b"{not json") == "malformed-json"
    assert _reason(codec, b"\xff\xfe") == "malformed-json"  # not UTF-8
    assert _reason(codec, b"[1, 2]") == "malformed-json"  # not an object
    assert _reason(codec, b"[" * 100_000) in ("malformed-json", "too-large")  # nested past the recursion limit
    msg = _msg(name)
    if "schema" in msg:
        assert _reason(codec, _dumps({**msg, "schema": msg["schema"][:-1] + "99"})) == "schema-version"
        assert _reason(codec, _dumps({k: v for k, v in msg.items() if k != "schema"})) == "schema-version"
    for token in (b"NaN", b"Infinity", b"-Infinity"):
        assert _reason(codec, _dumps(msg)[:-1] + b', "extra": ' + token + b"}") == "non-finite"


@pytest.mark.parametrize("name", ["batch", "locate", "pose"])
def test_oversized_client_messages_are_too_large(name):
    codec = C.CODECS[name]
    payload = _dumps(_msg(name))
    padded = payload[:-1] + b', "pad": "' + b"x" * (P.MAX_BATCH_BYTES - len(payload)) + b'"}'
    assert len(padded) > P.MAX_BATCH_BYTES
    assert _reason(codec, padded) == "too-large"
    assert codec.decode(padded[: len(payload) - 1] + b', "pad": ""}')  # the same message under the limit is taken


def test_batch_with_too_many_items_is_too_large():
    msg = _msg("batch")
    msg["marks"] = [{"t": 0.0, "x": 0.0, "y": 0.0, "floor": ""}] * (P.MAX_BATCH_ITEMS - len(msg["steps"]) - len(msg["scans"]) + 1)
    assert _reason(C.BATCH, _dumps(msg)) == "too-large"


def _numeric_paths(obj, path=()):
    """Paths of every number in a decoded JSON message."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _numeric_paths(v, path + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _numeric_paths(v, path + (i,))
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield path


def _with(msg, path, value):
    msg = json.loads(json.dumps(msg))
    node = msg
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return msg


NON_FINITE = [b"NaN", b"Infinity", b"-Infinity", b"1e999", b"-1e999"]
INTEGERS = {"seq", "acked_seq", "version"}  # integers on the wire: their reason is bad-seq / bad-value / count checks


@pytest.mark.parametrize("name", ["batch", "fix", "pose", "locate", "track", "map-version", "progress"])
def test_any_non_finite_number_is_non_finite(name):
    """Every number of the message, replaced by NaN, +-Infinity or an overflowing literal (1e999,
    which JSON parsers read as infinity): non-finite."""
    msg = _msg(name)
    paths = [p for p in _numeric_paths(msg) if p[-1] not in INTEGERS]

    @SETTINGS
    @given(st.sampled_from(paths), st.sampled_from(NON_FINITE))
    def check(path, token):
        payload = _dumps(_with(msg, path, "@@")).replace(b'"@@"', token)
        assert _reason(C.CODECS[name], payload) == "non-finite", (path, token)

    check()


@SETTINGS
@given(
    st.floats(allow_nan=False, allow_infinity=False).filter(lambda r: not RSSI_MIN_DBM <= r <= RSSI_MAX_DBM),
    st.integers(0, 1),
    st.sampled_from(["batch", "locate"]),
)
def test_any_rssi_outside_the_range_is_rssi_out_of_range(value, which, name):
    msg = _msg(name)
    scan = msg["scans"][0] if name == "batch" else msg["scan"]
    keys = list(scan["rssi"])
    scan["rssi"][keys[min(which, len(keys) - 1)]] = value
    assert _reason(C.CODECS[name], _dumps(msg)) == "rssi-out-of-range"


@SETTINGS
@given(
    st.sampled_from(["site", "device"]),
    st.text(max_size=80).filter(lambda s: not re.fullmatch(r"[A-Za-z0-9_.\-]{1,64}", s)) | st.none() | st.integers(),
)
def test_any_bad_id_is_bad_id(field, value):
    assert _reason(C.BATCH, _dumps({**_msg("batch"), field: value})) == "bad-id"


def test_batch_rejections():
    msg = _msg("batch")
    assert _reason(C.BATCH, _dumps(msg), site="site1", device="dev02") == "key-mismatch"
    assert _reason(C.BATCH, _dumps(msg), site="site2") == "key-mismatch"
    assert C.BATCH.decode(_dumps(msg), site="site1", device="dev01").seq == 17
    for seq in (0, -1, 1.5, "1", True, None):
        assert _reason(C.BATCH, _dumps({**msg, "seq": seq})) == "bad-seq", seq
    assert _reason(C.BATCH, _dumps({**msg, "seq": "@@"}).replace(b'"@@"', b"1e999")) == "bad-seq"
    assert _reason(C.BATCH, _dumps({**msg, "seq": "@@"}).replace(b'"@@"', b"1" * 5000)) == "malformed-json"  # past Python's int digits limit
    for rssi in ({}, [], "x"):
        assert _reason(C.BATCH, _dumps(_with(msg, ("scans", 0, "rssi"), rssi))) == "bad-scan"
    assert _reason(C.BATCH, _dumps(_with(msg, ("scans", 0, "tech"), "lora"))) == "bad-scan"
    assert _reason(C.BATCH, _dumps(_with(msg, ("steps", 0, "length"), -0.5))) == "bad-value"  # StepEvent's own check
    assert _reason(C.BATCH, _dumps(_with(msg, ("steps", 0, "t"), "soon"))) == "bad-value"
    assert _reason(C.BATCH, _dumps(_with(msg, ("steps", 1, "floor_change"), 1.5))) == "bad-value"
    assert _reason(C.BATCH, _dumps(_with(msg, ("steps", 1, "floor_change"), 10**400))) == "non-finite"  # no float holds it
    assert _reason(C.BATCH, _dumps({**msg, "sent_at": "yesterday"})) == "bad-value"
    del msg["steps"][0]["t"]
    assert _reason(C.BATCH, _dumps(msg)) == "malformed-json"
    assert _reason(C.BATCH, _dumps({**_msg("batch"), "steps": {"t": 1}})) == "malformed-json"
    assert _reason(C.BATCH, _dumps({**_msg("batch"), "marks": [1, 2]})) == "malformed-json"


def test_fix_pose_locate_ack_status_map_rejections():
    fix = _msg("fix")
    assert _reason(C.FIX, _dumps(_with(fix, ("fix", "cov"), [[1.0, 2.0], [2.0, 1.0]]))) == "bad-value"  # not positive definite
    assert _reason(C.FIX, _dumps(_with(fix, ("fix", "cov"), [[1.0, 0.0]]))) == "bad-value"
    assert _reason(C.FIX, _dumps(_with(fix, ("fix", "floor_prob"), 1.5))) == "bad-value"
    assert _reason(C.FIX, _dumps(_with(fix, ("fix", "source"), "sonar"))) == "bad-value"
    assert _reason(C.FIX, _dumps(_with(fix, ("floor_probs", "F1"), 2.0))) == "bad-value"
    assert _reason(C.FIX, _dumps(_with(fix, ("region", "mass"), 0.0))) == "bad-value"
    assert _reason(C.FIX, _dumps(_with(fix, ("region", "geometry"), {"type": "Point", "coordinates": [0, 0]}))) == "bad-value"
    assert _reason(C.FIX, _dumps(_with(fix, ("region", "geometry", "coordinates"), [[[[0, 0], [1]]]]))) == "bad-value"
    assert _reason(C.FIX, _dumps(_with(fix, ("fix",), [1, 2]))) == "malformed-json"
    assert _reason(C.POSE, _dumps(_with(_msg("pose"), ("cov", 0, 0), -1.0))) == "bad-value"
    assert _reason(C.POSE, _dumps({k: v for k, v in _msg("pose").items() if k != "x"})) == "malformed-json"
    assert _reason(C.LOCATE, _dumps(_with(_msg("locate"), ("scan",), None))) == "malformed-json"
    assert _reason(C.LOCATE, _dumps(_with(_msg("locate"), ("scan", "tech"), "lora"))) == "bad-scan"
    assert C.LOCATE.decode(_dumps(_with(_msg("locate"), ("scan", "rssi"), {}))).scan.rssi_dbm == {}  # answered with "no fix"
    # a locate's scan within the physical limits (hybridloc.wire.limits): beyond them refused whole,
    # stale readings dropped (none left: answered with "no fix")
    big = {f"ap{i}": -70.0 for i in range(L.MAX_SCAN_READINGS + 1)}
    assert _reason(C.LOCATE, _dumps(_with(_msg("locate"), ("scan", "rssi"), big))) == "scan-too-large"
    assert _reason(C.LOCATE, _dumps(_with(_msg("locate"), ("scan", "t"), 1.7e12))) == "wrong-units"  # milliseconds
    loc = _msg("locate")
    (tx0, *_) = loc["scan"]["rssi"]
    loc["scan"]["age"] = {k: (1e4 if k == tx0 else 1.0) for k in loc["scan"]["rssi"]}
    assert tx0 not in C.LOCATE.decode(_dumps(loc)).scan.rssi_dbm
    for seq in (-1, 1.5, None):
        assert _reason(C.ACK, _dumps({**_msg("ack"), "acked_seq": seq})) == "bad-seq"
    assert _reason(C.ACK, _dumps({**_msg("ack"), "device": "a/b"})) == "bad-id"
    assert _reason(C.STATUS, _dumps({**_msg("status"), "online": "dev01"})) == "malformed-json"
    assert _reason(C.STATUS, _dumps({**_msg("status"), "counts": {"x": 1.5}})) == "bad-value"
    assert _reason(C.MAP_INFO, _dumps({"site": "site1", "version": 0})) == "bad-value"
    assert _reason(C.MAP_INFO, _dumps({"site": "s/1", "version": 1})) == "bad-id"


# ---------------------------------------------------------------------------------------------- nothing else escapes
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner, max_size=3),
    max_leaves=8,
)


def _paths(obj, path=()):
    yield path
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, path + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, path + (i,))


@pytest.mark.parametrize("name", sorted(MESSAGES))
def test_a_decoder_raises_nothing_but_rejected(name):
    """Any part of a valid message replaced by any JSON value (or the payload by any bytes): the
    decoder returns a record or refuses with a known reason; no other exception reaches the server."""
    codec = C.CODECS[name]
    msg = _msg(name)
    paths = [p for p in _paths(msg) if p]

    @SETTINGS
    @given(st.sampled_from(paths), json_values, st.binary(max_size=64))
    def check(path, value, raw):
        for payload in (json.dumps(_with(msg, path, value)).encode(), raw):
            try:
                codec.decode(payload)
            except P.Rejected as exc:
                assert exc.reason in REASONS

    check()


def test_batch_end_of_walk_is_optional_and_round_trips():
    from hybridloc.wire import codecs as C
    from hybridloc.wire.messages import Batch
    from hybridloc.wire.protocol import Rejected

    plain = Batch("site1", "dev01", 3)
    marked = Batch("site1", "dev01", 4, end_of_walk=True)
    assert b"end_of_walk" not in C.BATCH.encode(plain)  # older servers and clients see the bytes they know
    assert C.BATCH.decode(C.BATCH.encode(marked)).end_of_walk is True
    assert C.BATCH.decode(C.BATCH.encode(plain)).end_of_walk is False
    bad = C.BATCH.encode(plain).replace(b'"seq":3', b'"seq":3,"end_of_walk":"yes"')
    with pytest.raises(Rejected) as exc:
        C.BATCH.decode(bad)
    assert exc.value.reason == "bad-value"


# ---------------------------------------------------------------------------------------------- crowd SLAM messages
def test_track_rejections():
    msg = _msg("track")
    assert C.TRACK.decode(_dumps(msg), site="site1", device="dev01").walk_id == 42
    assert _reason(C.TRACK, _dumps(msg), site="site1", device="dev02") == "key-mismatch"
    assert _reason(C.TRACK, _dumps({**msg, "device": "a/b"})) == "bad-id"
    for field, bad in (("walk_id", 0), ("walk_id", 1.5), ("walk_id", True), ("walk_id", None), ("run", 0), ("run", "7"), ("map_version", 0)):
        assert _reason(C.TRACK, _dumps({**msg, field: bad})) == "bad-value", (field, bad)
    assert C.TRACK.decode(_dumps({**msg, "map_version": None})).map_version is None
    assert _reason(C.TRACK, _dumps({**msg, "x": msg["x"][:-1]})) == "bad-value"  # lengths disagree
    assert _reason(C.TRACK, _dumps({**msg, "kind": msg["kind"] + ["step"]})) == "bad-value"
    assert _reason(C.TRACK, _dumps({**msg, "cov": msg["cov"][:-1]})) == "bad-value"
    assert _reason(C.TRACK, _dumps({**msg, "t": [3.0, 2.0, 4.0]})) == "bad-value"  # times decrease
    assert C.TRACK.decode(_dumps({**msg, "t": [2.0, 2.0, 2.0]})).track.t.tolist() == [2.0] * 3  # equal times are fine
    assert _reason(C.TRACK, _dumps(_with(msg, ("kind", 1), "walk"))) == "bad-value"
    assert _reason(C.TRACK, _dumps({**msg, "anchored": "gps"})) == "bad-value"
    assert _reason(C.TRACK, _dumps({**msg, "scale": 0.0})) == "bad-value"
    assert _reason(C.TRACK, _dumps(_with(msg, ("cov", 0), [1.0, 2.0, 1.0]))) == "bad-value"  # xy^2 > xx yy: not PSD
    assert _reason(C.TRACK, _dumps(_with(msg, ("cov", 0), [-1.0, 0.0, 1.0]))) == "bad-value"
    assert _reason(C.TRACK, _dumps(_with(msg, ("cov", 0), [1.0, 0.0]))) == "bad-value"
    singular = C.TRACK.decode(_dumps(_with(msg, ("cov", 0), [1.0, 1.0, 1.0]))).track.cov[0]  # PSD, not PD: taken
    assert singular.tolist() == [[1.0, 1.0], [1.0, 1.0]]
    assert _reason(C.TRACK, _dumps({**msg, "floor": [["F1", 2]]})) == "bad-value"  # runs cover 2 of 3 points
    assert _reason(C.TRACK, _dumps({**msg, "floor": [["F1", 10**12]]})) == "bad-value"  # refused, never allocated
    assert _reason(C.TRACK, _dumps({**msg, "floor": [["F1", 0], ["F2", 3]]})) == "bad-value"
    assert _reason(C.TRACK, _dumps({**msg, "floor": [["F1", 2], "F2"]})) == "malformed-json"
    assert _reason(C.TRACK, _dumps({**msg, "t": "soon"})) == "malformed-json"
    assert _reason(C.TRACK, _dumps({**msg, "cov": None})) == "malformed-json"
    assert _reason(C.TRACK, _dumps(_with(msg, ("x", 0), "east"))) == "bad-value"


def test_track_limits_and_the_encoder_keeps_the_newest_points():
    n = P.MAX_TRACK_POINTS + 25
    tr = CorrectedTrack(
        None, np.arange(n) * 0.5, np.column_stack([np.arange(n) * 0.7, np.zeros(n)]), np.tile(np.eye(2) * 0.04, (n, 1, 1)),
        ("F1",) * n, ("step",) * n, "loops", 0.97, 0.01,
    )  # fmt: skip
    payload = C.TRACK.encode(Track("site1", "dev01", 5, None, 2, tr))
    assert len(payload) <= P.MAX_TRACK_BYTES
    back = C.TRACK.decode(payload).track
    assert len(back) == P.MAX_TRACK_POINTS and back.t[0] == tr.t[25] and back.t[-1] == tr.t[-1]  # the newest, the oldest dropped
    assert np.array_equal(back.pos_enu, tr.pos_enu[25:]) and (back.scale, back.heading_bias, back.anchored) == (0.97, 0.01, "loops")
    # a decoder refuses more points than the limit, and more bytes
    msg = json.loads(payload)
    msg.update(t=msg["t"] + [msg["t"][-1]], x=msg["x"] + [0.0], y=msg["y"] + [0.0], cov=msg["cov"] + [None], kind=msg["kind"] + ["scan"])
    msg["floor"][-1][1] += 1
    assert _reason(C.TRACK, _dumps(msg)) == "too-large"
    small = _dumps(_msg("track"))
    padded = small[:-1] + b', "pad": "' + b"x" * (P.MAX_TRACK_BYTES - len(small)) + b'"}'
    assert len(padded) > P.MAX_TRACK_BYTES and _reason(C.TRACK, padded) == "too-large"
    # a payload the point count allows but the byte limit does not (floor names of escaped characters,
    # a new floor at every point): the encoder keeps fewer of the newest points, never sends what is refused
    m = P.MAX_TRACK_POINTS
    floors = tuple(chr(0x1F600 + i % 2) * 32 for i in range(m))  # 32 characters, 12 bytes each escaped (a surrogate pair)
    wide = CorrectedTrack(None, np.arange(m) * 0.5, np.zeros((m, 2)), np.tile(np.eye(2), (m, 1, 1)), floors, ("scan",) * m, "map")
    whole = json.dumps(C.TRACK._message(Track("site1", "dev01", 5, None, 2, wide), 0), separators=(",", ":")).encode()
    assert len(whole) > P.MAX_TRACK_BYTES  # what the encoder must not send
    payload = C.TRACK.encode(Track("site1", "dev01", 5, None, 2, wide))
    back = C.TRACK.decode(payload).track
    assert len(payload) <= P.MAX_TRACK_BYTES and 0 < len(back) < m and back.t[-1] == wide.t[-1] and back.floor[-1] == floors[-1]


def test_track_record_fills_or_checks_its_walk_id():
    tr = CorrectedTrack(None, [1.0], [[0.0, 0.0]], [np.eye(2)], ("F1",), ("step",))
    assert Track("site1", "dev01", 9, None, 1, tr).track.walk_id == 9
    with pytest.raises(ValueError):
        Track("site1", "dev01", 9, None, 1, CorrectedTrack(8, [1.0], [[0.0, 0.0]], [np.eye(2)], ("F1",), ("step",)))


def test_map_version_progress_and_status_slam_rejections():
    mv = _msg("map-version")
    for field, bad in (("version", 0), ("version", 1.5), ("walks", -1), ("coverage", 1.5), ("coverage", -0.1), ("created_at", "now")):
        assert _reason(C.MAP_VERSION, _dumps({**mv, field: bad})) == "bad-value", (field, bad)
    assert _reason(C.MAP_VERSION, _dumps({**mv, "source": "guess"})) == "bad-value"
    assert _reason(C.MAP_VERSION, _dumps({**mv, "site": "a b"})) == "bad-id"
    assert C.MAP_VERSION.decode(_dumps({**mv, "coverage": None})).coverage is None
    pr = _msg("progress")
    assert _reason(C.PROGRESS, _dumps({**pr, "done": 8})) == "bad-value"  # done > total
    assert _reason(C.PROGRESS, _dumps({**pr, "total": -1})) == "bad-value"
    assert _reason(C.PROGRESS, _dumps({**pr, "stage": ""})) == "bad-value"
    assert _reason(C.PROGRESS, _dumps({**pr, "stage": 3})) == "malformed-json"
    assert C.PROGRESS.decode(_dumps({**pr, "stage": "s" * 40})).stage == "s" * 32  # cut, as every text
    # status: slam is optional (an older server's payload decodes with {}), per site an object
    old = (
        b'{"schema": "hybridloc.status/1", "online": ["dev01"], "counts": {"batches-received": 3}, "db": {"devices": 1}, "maps_loaded": {"site1": 2}}'
    )
    st_old = C.STATUS.decode(old)
    assert st_old.slam == {} and st_old.as_dict()["slam"] == {}
    assert C.STATUS.encode(st_old) == old
    st_new = C.STATUS.decode(C.STATUS.encode(Status(slam={"site1": {"walks_pending": 2, "coverage": None}})))
    assert st_new.as_dict()["slam"] == {"site1": {"walks_pending": 2, "coverage": None}}
    assert _reason(C.STATUS, _dumps({**json.loads(old), "slam": {"site1": 3}})) == "malformed-json"
    assert _reason(C.STATUS, _dumps({**json.loads(old), "slam": [1]})) == "malformed-json"
    # status: rejections per device are optional too (older servers send none: {}), each a count >= 0
    assert st_old.rejections == {} and st_old.as_dict()["rejections"] == {}
    st_rej = C.STATUS.decode(C.STATUS.encode(Status(rejections={"dev01": {"duplicate": 2, "step-too-long": 1}})))
    assert st_rej.rejections == {"dev01": {"duplicate": 2, "step-too-long": 1}}
    for bad in ({"dev01": 3}, [1]):
        assert _reason(C.STATUS, _dumps({**json.loads(old), "rejections": bad})) == "malformed-json"
    for bad in ({"dev01": {"duplicate": -1}}, {"dev01": {"duplicate": 1.5}}, {"dev01": {"duplicate": True}}):
        assert _reason(C.STATUS, _dumps({**json.loads(old), "rejections": bad})) == "bad-value"


# ---------------------------------------------------------------------------------------------- fast JSON path
_json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**80), max_value=2**80)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(alphabet="0123456789abc:\u00e9\u2603\ud7ff", max_size=30),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=20,
)


def _slow_or_reason(payload: bytes):
    try:
        return C._load_slow(payload)
    except P.Rejected as rej:
        return ("rejected", rej.reason)


def _fast_or_reason(payload: bytes):
    try:
        return C._load(payload, None)
    except P.Rejected as rej:
        return ("rejected", rej.reason)


# JSON text put in as one more member: what json and orjson read differently, or refuse
_TAILS = ["", "NaN", "Infinity", "-Infinity", "1e999", r'"\ud800"', "123456789012345678901234567890", "9" * 4300, "9" * 4301, "[" * 3000]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(st.text(max_size=8), _json_values, max_size=6), st.sampled_from(_TAILS))
def test_fast_json_reads_what_the_standard_parser_reads(obj, tail):
    """The decoders' msgspec path accepts exactly what json accepts, with the same values (big integers
    exact), and every refusal keeps json's reason (NaN, overflowing literals, lone surrogates, nesting)."""
    text = json.dumps(obj)
    if tail:
        text = text[:-1] + (", " if obj else "") + f'"z": {tail}' + "}"
    payload = text.encode()
    fast, slow = _fast_or_reason(payload), _slow_or_reason(payload)
    assert fast == slow
    if isinstance(slow, dict):
        assert json.dumps(fast, sort_keys=True) == json.dumps(slow, sort_keys=True)  # ints stay ints, floats floats


_step_value = (
    st.floats(allow_nan=True, allow_infinity=True, width=64)
    | st.floats(min_value=-10, max_value=10)
    | st.integers(min_value=-(2**60), max_value=2**60)
    | st.booleans()
    | st.none()
    | st.text(max_size=40)
)
_STEP_KEYS = [f.name for f in dataclasses.fields(StepEvent)]


def _outcome(fn, s):
    try:
        r = C._structure(fn, s)
    except P.Rejected as rej:
        return ("rejected", rej.reason)
    return (r, [(k, type(getattr(r, k))) for k in _STEP_KEYS])


_finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)


@st.composite
def _step_dicts(draw):
    """A well-formed step (every field a finite float, or the optional ones left out), then up to two
    fields replaced by anything or removed: the fast path's edges."""
    s = {k: draw(_finite) for k in _STEP_KEYS if k not in ("floor_change", "degraded")}
    s.update(length=abs(s["length"]), sigma_length=abs(s["sigma_length"]), sigma_heading=abs(s["sigma_heading"]))
    s.update(sigma_height_change=abs(s["sigma_height_change"]), floor_change=draw(st.integers(-3, 3)), degraded=draw(st.sampled_from(["", "no-mag"])))
    for k in draw(st.lists(st.sampled_from(_STEP_KEYS + ["extra"]), max_size=2)):
        if draw(st.booleans()):
            s[k] = draw(_step_value)
        else:
            s.pop(k, None)
    return s


@settings(max_examples=1500, deadline=None)
@given(_step_dicts())
@example({"t": 1.0, "length": 0.7, "heading": 0.1, "sigma_length": 0.1, "sigma_heading": 0.1, "floor_change": 10**17 + 1})  # past a float's integers
@example({"t": 1.0, "length": 0.7, "heading": 0.1, "sigma_length": 0.1, "sigma_heading": 0.1, "sigma_height_change": -1.0})
def test_fast_step_decoding_gives_the_checked_steps(s):
    """A step dict read by the fast path equals the checked path's step (values and their types), and
    one the fast path declines gets the checked path's reason."""
    assert _outcome(C._step_from, s) == _outcome(C._step_checked, s)


# ---------------------------------------------------------------------------------------------- the batch's typed fast path
_any_value = (
    st.floats(allow_nan=False, allow_infinity=False, width=64)
    | st.floats(min_value=-400, max_value=400)
    | st.integers(min_value=-(2**70), max_value=2**70)
    | st.booleans()
    | st.none()
    | st.text(max_size=70)
    | st.lists(st.integers(), max_size=2)
    | st.dictionaries(st.text(max_size=3), st.floats(-150, 10), max_size=2)
)


@st.composite
def _batch_dicts(draw):
    """A plain batch as a client sends it (steps at a walker's pace, scans and marks in time order), then
    up to three changes anywhere: a field replaced by anything or removed, an item moved, a time pushed
    past a limit - the fast path's edges, and the general path's every reason."""
    n_steps, n_scans, n_marks = draw(st.integers(0, 6)), draw(st.integers(0, 3)), draw(st.integers(0, 2))
    t0 = draw(st.floats(0, 1e6))
    steps = [
        {"t": t0 + 0.5 * i, "length": draw(st.floats(0, 1.5)), "heading": draw(st.floats(-7, 7)), "sigma_length": 0.05, "sigma_heading": 0.1}
        for i in range(n_steps)
    ]
    for s in steps:
        if draw(st.booleans()):
            s.update(heading_change=draw(st.floats(-3.5, 3.5)), sigma_heading_change=0.02)
    scans = [
        {
            "t": t0 + 1.0 * i,
            "tech": draw(st.sampled_from(["wifi", "ble"])),
            "rssi": {f"ap{j}": draw(st.floats(-100, -20)) for j in range(draw(st.integers(1, 4)))},
        }
        for i in range(n_scans)
    ]
    for sc in scans:
        if draw(st.booleans()):
            sc["freq"] = {k: 2.412e9 for k in sc["rssi"]}
        if draw(st.booleans()):
            sc["age"] = {k: draw(st.floats(0, 5)) for k in sc["rssi"]}
    marks = [{"t": t0 + 2.0 * i, "x": draw(st.floats(-50, 50)), "y": 1.0, "floor": "F1"} for i in range(n_marks)]
    msg = {
        "schema": P.BATCH_SCHEMA,
        "site": "s1",
        "device": "d1",
        "seq": draw(st.integers(1, 5)),
        "device_model": "m",
        "sent_at": 1.0,
        "steps": steps,
        "scans": scans,
        "marks": marks,
    }
    for _ in range(draw(st.integers(0, 3))):
        where = draw(st.sampled_from(["top", "steps", "scans", "marks"]))
        items = msg.get(where) if where != "top" else None
        listed = isinstance(items, list) and items and all(isinstance(x, dict) for x in items)
        target = draw(st.sampled_from(items)) if listed else msg
        key = draw(st.sampled_from(sorted(set(target) | {"heading_change", "floor_change", "degraded", "end_of_walk", "freq", "age", "extra"})))
        action = draw(st.sampled_from(["replace", "remove", "far", "swap"]))
        if action == "remove":
            target.pop(key, None)
        elif action == "far" and isinstance(target.get(key), (int, float)) and not isinstance(target.get(key), bool):
            target[key] = target[key] + draw(st.sampled_from([-1e12, -400.0, 400.0, 1e12]))
        elif action == "swap" and listed and len(items) > 1:
            items.reverse()
        else:
            target[key] = draw(_any_value)
    return msg


def _batch_outcome(fn, payload: bytes):
    try:
        b = fn(payload, "s1", "d1")
    except P.Rejected as rej:
        return ("rejected", rej.reason)
    scans = [(s.t, s.technology, dict(s.rssi_dbm), dict(s.frequency_hz), dict(s.age_s), s.device_model, type(s.t)) for s in b.scans]
    steps = [(s, [(k, type(getattr(s, k))) for k in _STEP_KEYS]) for s in b.steps]
    return (b.site, b.device, b.seq, b.device_model, b.sent_at, b.end_of_walk, b.refused, steps, scans, list(b.marks))


@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_batch_dicts())
def test_the_typed_fast_path_decodes_batches_as_the_general_path_does(msg):
    """Whatever a batch holds, the decoder (typed fast path first) gives the general path's batch -
    values, their types, what limits.screen refused - or its reason for refusing it."""
    payload = json.dumps(msg).encode()
    assert _batch_outcome(C.BATCH.decode, payload) == _batch_outcome(C.BATCH.decode_general, payload)


def test_the_fast_path_takes_plain_batches():
    """A client's own batch is decoded by the typed path (the point of it), a batch with anything to
    refuse or count by the general one."""
    b = Batch(
        "s1", "d1", 3, "m", tuple(StepEvent(0.5 * i, 0.7, 0.1, 0.05, 0.1, 0.01, 0.02) for i in range(1, 50)),
        (RfScan(1.0, "wifi", {"ap1": -50.0, "ap2": -60.5}, {"ap1": 2.4e9}, {"ap2": 1.0}),), (SurveyMark(2.0, 1.0, 2.0, "F1"),),
    )  # fmt: skip
    payload = C.BATCH.encode(b)
    assert C._batch_fast(payload, "s1", "d1") is not None
    too_long = payload.replace(b'"length":0.7', b'"length":7.0', 1)
    assert C._batch_fast(too_long, "s1", "d1") is None and C.BATCH.decode(too_long, "s1", "d1").refused == (("step-too-long", 1),)


# ---------------------------------------------------------------------------------------------- the columnar form of a batch's steps
#: what a step field left out reads as (the required fields have none: their absence is refused)
_ABSENT = {"heading_change": None, "sigma_heading_change": None, "height_change": 0.0, "sigma_height_change": 0.0, "floor_change": 0, "degraded": ""}


def _columns(rows: list) -> tuple[dict, bool]:
    """The columnar form of step rows as sent: a column per key any row has, a row without the key given
    what its absence reads as (None for a required or unknown key); and whether that form says exactly
    what the rows said (no required or unknown key was missing anywhere)."""
    names = list(dict.fromkeys(k for r in rows for k in r))
    exact = all(k in r or k in _ABSENT for r in rows for k in names)
    return {k: [r.get(k, _ABSENT.get(k)) for r in rows] for k in names}, exact


def _rows(columns: dict) -> list:
    """Step i of a columnar form: each column's i-th value under the column's name (docs/protocol.md)."""
    return [dict(zip(columns, values)) for values in zip(*columns.values())]


@st.composite
def _columnar_batch_dicts(draw):
    """A batch of :func:`_batch_dicts` (a client's, then up to three changes anywhere) with its steps in
    the columnar form, then maybe one change of the columns themselves: one left out, one that is not a
    list, one cut short, an unknown one, a value replaced by anything."""
    msg = draw(_batch_dicts())
    if not (isinstance(msg.get("steps"), list) and all(isinstance(s, dict) for s in msg["steps"])):
        return msg, None, False
    rows = msg["steps"]
    cols, exact = _columns(rows)
    col_msg = dict(msg, steps=cols)
    change = draw(st.sampled_from(["none", "none", "drop", "not-list", "short", "unknown", "value"]))
    names = sorted(cols)
    if change != "none" and names:
        exact = False
        k = draw(st.sampled_from(names))
        if change == "drop":
            del cols[k]
        elif change == "not-list":
            cols[k] = draw(_any_value.filter(lambda v: not isinstance(v, list)))
        elif change == "short" and cols[k]:
            cols[k] = cols[k][:-1]
        elif change == "unknown":
            cols["extra"] = [draw(_any_value) for _ in cols[k]]
        elif change == "value" and cols[k]:
            cols[k][draw(st.integers(0, len(cols[k]) - 1))] = draw(_any_value)
    return col_msg, rows, exact


@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_columnar_batch_dicts())
@example(({"schema": P.BATCH_SCHEMA, "site": "s1", "device": "d1", "seq": 1, "steps": {"t": [1.0, 2.0], "length": [0.7, 7.0], "heading": [0.1, 0.1],
           "sigma_length": [0.05, 0.05], "sigma_heading": [0.1, 0.1]}}, None, False))  # fmt: skip
def test_columnar_steps_decode_as_their_rows(case):
    """A batch with its steps as columns decodes (typed path first) as the general path decodes it, and,
    when its columns are whole (lists of one length), as the same batch with step i made of each column's
    i-th value: the same steps, the same rejection reason, the same items refused and counted by limit;
    when the columns say exactly what the original rows said, as those rows."""
    msg, rows, exact = case
    payload = json.dumps(msg).encode()
    got = _batch_outcome(C.BATCH.decode, payload)
    assert got == _batch_outcome(C.BATCH.decode_general, payload)
    cols = msg.get("steps")
    if isinstance(cols, dict) and all(isinstance(c, list) for c in cols.values()) and len({len(c) for c in cols.values()}) <= 1:
        as_rows = json.dumps(dict(msg, steps=_rows(cols))).encode()
        assert got == _batch_outcome(C.BATCH.decode_general, as_rows) == _batch_outcome(C.BATCH.decode, as_rows)
    if exact:
        assert got == _batch_outcome(C.BATCH.decode, json.dumps(dict(msg, steps=rows)).encode())


def test_columnar_steps_refusals():
    """Columns that are not lists are malformed-json, columns of unequal lengths bad-value; a value beyond
    a limit is left out and counted as in rows; the columnar batch is the typed path's when plain."""
    b = Batch("s1", "d1", 3, "m", tuple(StepEvent(0.5 * i, 0.7, 0.1, 0.05, 0.1, 0.01, 0.02) for i in range(1, 50)))
    payload = C.BATCH.encode(b, step_columns=True)
    assert C._batch_fast(payload, "s1", "d1") is not None
    msg = json.loads(payload)
    for cols, reason in (
        (dict(msg["steps"], length=0.7), "malformed-json"),
        (dict(msg["steps"], length=msg["steps"]["length"][:-1]), "bad-value"),
        ({k: v for k, v in msg["steps"].items() if k != "t"}, "malformed-json"),
        (dict(msg["steps"], t=[None] * 49), "bad-value"),
    ):
        with pytest.raises(P.Rejected) as e:
            C.BATCH.decode(json.dumps(dict(msg, steps=cols)).encode(), "s1", "d1")
        assert e.value.reason == reason, (cols.keys(), e.value)
    too_long = dict(msg["steps"], length=[7.0] + msg["steps"]["length"][1:])
    got = C.BATCH.decode(json.dumps(dict(msg, steps=too_long)).encode(), "s1", "d1")
    assert got.refused == (("step-too-long", 1),) and len(got.steps) == 48


@SETTINGS
@given(batches())
def test_both_step_forms_decode_to_the_same_batch(b):
    """A batch encoded with its steps as columns decodes as the same batch encoded with rows (today's
    bytes): the optional fields travel by the same rules."""
    rows, cols = C.BATCH.encode(b), C.BATCH.encode(b, step_columns=True)
    assert _batch_outcome(C.BATCH.decode, cols) == _batch_outcome(C.BATCH.decode, rows)
    assert C.BATCH.decode(cols).steps == C.BATCH.decode(rows).steps


def test_step_columns_hold_the_steps_without_making_them():
    """The decoder's StepColumns: a sequence equal to the steps' tuple, indexable, sliceable."""
    steps = tuple(
        StepEvent(
            0.5 * i,
            0.7,
            3.0 * i,
            0.05,
            0.1,
            *((None, None) if i % 2 else (0.01, 0.02)),
            *((0.1, 0.01) if i % 3 else (0.0, 0.0)),
            i % 2,
            "gap" * (i % 2),
        )
        for i in range(1, 9)
    )
    got = C.BATCH.decode(C.BATCH.encode(Batch("s1", "d1", 1, "", steps), step_columns=True)).steps
    assert isinstance(got, StepColumns) and len(got) == 8
    assert got == steps and steps == got and tuple(got) == steps and got[3] == steps[3] and got[-1] == steps[-1] and got[2:5] == steps[2:5]
    assert got != steps[:-1] and C.step_times(got) == [s.t for s in steps]


def test_fix_region_geometry_is_shapelys_geojson():
    """The fix's region is written from coordinate arrays; the JSON is the one shapely's mapping gives
    (holes, several parts, a single polygon made a MultiPolygon by the record)."""
    import json

    import shapely
    from shapely.geometry import mapping

    from hybridloc.types import AbsoluteFix, ContainmentRegion, Fix

    ring = shapely.Polygon([(0, 0), (10, 0), (10, 10), (0, 10)], [[(2, 2), (4, 2), (4, 4), (2, 4)]])
    discs = shapely.union_all(shapely.buffer(shapely.points([[0.0, 0.0], [3.0, 0.0], [40.0, 1.0 / 3.0]]), 2.0))
    fix = AbsoluteFix(1.0, [1.0, 2.0], np.diag([4.0, 9.0]), "wifi", "F1", 0.9)
    for area in (ring, discs):
        region = ContainmentRegion("F1", area, 0.95, 1.0)
        msg = json.loads(C.FIX.encode(Fix(fix, region, {"F1": 1.0})))
        assert json.dumps(msg["region"]["geometry"]) == json.dumps(mapping(region.area))
        back = C.FIX.decode(C.FIX.encode(Fix(fix, region, {"F1": 1.0})))
        assert back.region is not None and back.region.area.equals(region.area)


_EDGE = [0.0, -0.0, 1e-300, -1e-300, math.nan, math.inf, -math.inf, math.pi, -math.pi, 2 * math.pi, 2 * math.pi + 1e-12, 5.0, 5.0 + 1e-12, 2.0, -2.0, 0.05, 1e11, -1e11]  # fmt: skip
_step_float = st.one_of(st.floats(-10.0, 10.0), st.sampled_from(_EDGE), st.floats(allow_nan=True, allow_infinity=True))


@st.composite
def _step_columns(draw):
    """11 step columns of one length (1-16): times mostly increasing at a walker's rate; each other
    column mostly plausible values (headings up to +-6.3 rad, past the 2 pi limit), else values near and
    past every limit, NaN and infinities; absent heading changes."""
    n = draw(st.integers(1, 16))
    if draw(st.integers(0, 4)):
        t0 = draw(st.floats(-1e6, 1e6))
        jitter = st.floats(-0.2, 0.2) if draw(st.integers(0, 3)) else st.sampled_from([0.0, -0.46, -0.45, 1e-9])
        t = [t0 + 0.5 * i + draw(jitter) for i in range(n)]
    else:
        t = [draw(_step_float) for _ in range(n)]

    def col(good, none=False):
        vals = good if draw(st.integers(0, 15)) else st.one_of(good, _step_float)
        return [draw(st.one_of(st.none(), vals) if none else vals) for _ in range(n)]

    small, angle = st.floats(0.0, 1.5), st.floats(-6.3, 6.3)
    fc = col(st.integers(-3, 3)) if draw(st.integers(0, 5)) else [draw(st.integers(-300, 300)) for _ in range(n)]
    dg = [draw(st.sampled_from(["", "saturated"] if draw(st.integers(0, 5)) else ["", "x" * 33])) for _ in range(n)]
    return (t, col(small), col(angle), col(small), col(small), col(angle, True), col(small, True), col(st.floats(-1.0, 1.0)), col(small), fc, dg)


@settings(max_examples=1500, deadline=None)
@given(_step_columns())
def test_few_steps_are_checked_in_python_as_numpy_checks_them(cols):
    """A live batch's few steps are checked one by one in Python (codecs._steps_scalar, the server's
    decoding at 1,000 clients): the same verdict and the same values, bit for bit, as the numpy path."""
    a, b = C._steps_scalar(*cols), C._steps_numpy(*cols)
    assert (a is None) == (b is None)
    if a is not None:
        assert repr(a.columns) == repr(b.columns)


def test_a_lone_surrogate_is_not_text():
    """An escaped lone surrogate ("\\ud800") reads as a string no UTF-8 can hold: refused as malformed
    JSON on both parsers' paths (stored, it failed the database's encoding and rolled back its whole
    group of batches); a surrogate pair is a character like any other."""
    base = {"schema": P.BATCH_SCHEMA, "site": "s1", "device": "d1", "seq": 1, "steps": []}
    lone = [
        dict(base, scans=[{"t": 1.0, "tech": "wifi", "rssi": {"\ud800": -50.0}}]),
        dict(base, marks=[{"t": 1.0, "x": 0.0, "y": 0.0, "floor": "F\udfff"}]),
        dict(base, device_model="\udb00"),
    ]
    for msg in lone:
        payload = json.dumps(msg).encode()  # json escapes the surrogate: ASCII bytes
        for decode in (C.BATCH.decode, C.BATCH.decode_general):
            with pytest.raises(P.Rejected) as e:
                decode(payload, "s1", "d1")
            assert e.value.reason == "malformed-json"
    pair = json.dumps(dict(base, scans=[{"t": 1.0, "tech": "wifi", "rssi": {"\ud83d\ude00": -50.0}}])).encode()
    assert list(C.BATCH.decode(pair, "s1", "d1").scans[0].rssi_dbm) == ["\U0001f600"]
