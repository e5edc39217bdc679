"""Records that exist only on the wire: the batch (the unit of delivery), its acknowledgement, the
locate request, the server's status, the radio map's attachment, and what the crowd SLAM tells the
clients (a device's corrected track, a new map version, a running job's progress).

The records every layer shares (:class:`~hybridloc.types.StepEvent`, :class:`~hybridloc.types.RfScan`,
:class:`~hybridloc.types.SurveyMark`, :class:`~hybridloc.types.Fix`, :class:`~hybridloc.types.Pose`)
live in :mod:`hybridloc.types`; :mod:`.codecs` turns all of them into bytes and back.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, overload

from ..types import CorrectedTrack, RfScan, StepEvent, SurveyMark


class StepColumns(Sequence[StepEvent]):
    """Steps held as columns: a list per :class:`~hybridloc.types.StepEvent` field, in its order, a step
    per index, values already checked and as the records hold them (headings wrapped ...). Each step is
    made when asked for, so a decoded batch of a thousand steps is stored without making a thousand
    records (the server reads :attr:`columns`); it equals any sequence of the same steps."""

    __slots__ = ("columns",)

    def __init__(self, columns: Sequence[list]):
        if len(columns) != len(_STEP_FIELDS) or len({len(c) for c in columns}) > 1:
            raise ValueError(f"StepColumns: {len(_STEP_FIELDS)} columns of one length expected")
        self.columns: tuple[list, ...] = tuple(columns)

    def __len__(self) -> int:
        return len(self.columns[0])

    @overload
    def __getitem__(self, i: int) -> StepEvent: ...
    @overload
    def __getitem__(self, i: slice) -> tuple[StepEvent, ...]: ...
    def __getitem__(self, i: int | slice) -> StepEvent | tuple[StepEvent, ...]:
        if isinstance(i, slice):
            return tuple(self)[i]
        return StepEvent._checked_already(dict(zip(_STEP_FIELDS, (c[i] for c in self.columns))))

    def __iter__(self) -> Iterator[StepEvent]:
        new = StepEvent._checked_already
        return (new(dict(zip(_STEP_FIELDS, r))) for r in zip(*self.columns))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sequence) or isinstance(other, (str, bytes)):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other))

    def __hash__(self) -> int:
        return hash(tuple(self))

    def __repr__(self) -> str:
        return f"StepColumns({len(self)} steps)"


_STEP_FIELDS = tuple(f.name for f in dataclasses.fields(StepEvent))


@dataclass(frozen=True, eq=False)
class Batch:
    """A client's batch of records, with its per-device sequence number (go-back-N, see
    :mod:`.protocol`).

    Attributes
    ----------
    site, device : str
        Ids (:func:`~.protocol.check_id`).
    seq : int
        Sequence number, from 1 per device.
    device_model : str
        Phone or IMU model; empty when unknown. Every scan of a decoded batch carries it too.
    steps, scans, marks : tuples of StepEvent, RfScan, SurveyMark
        (the decoder may give the steps as :class:`StepColumns`, a sequence that equals the tuple)
    sent_at : float
        When the client sent the batch, s (Unix time on the client; 0 when unknown).
    end_of_walk : bool
        The device's walk ends with this batch (its replay or live input ended): the server closes the
        walk at once instead of after the idle gap. On the wire only when true (older clients omit it).
    refused : tuple of (reason, count)
        Items the decoder left out for breaking a physical limit (:mod:`.limits`), counted by reason,
        sorted; never on the wire (a decoded batch says what its sender's bytes carried beyond it).
    """

    site: str
    device: str
    seq: int
    device_model: str = ""
    steps: Sequence[StepEvent] = ()
    scans: tuple[RfScan, ...] = ()
    marks: tuple[SurveyMark, ...] = ()
    sent_at: float = 0.0
    end_of_walk: bool = False
    refused: tuple[tuple[str, int], ...] = ()

    def __post_init__(self) -> None:
        for name in ("steps", "scans", "marks", "refused"):
            v = getattr(self, name)
            if not isinstance(v, StepColumns):
                object.__setattr__(self, name, tuple(v))

    def to_json(self) -> bytes:
        """Deprecated: ``codecs.BATCH.encode(batch)``."""
        from .codecs import BATCH

        return BATCH.encode(self)


@dataclass(frozen=True)
class Ack:
    """The server's acknowledgement: every batch of ``device`` up to ``acked_seq`` is persisted."""

    device: str
    acked_seq: int


@dataclass(frozen=True, eq=False)
class LocateRequest:
    """A ``locate`` query: one scan (its ``device_model`` says whose receiver heard it)."""

    scan: RfScan


@dataclass(frozen=True)
class Status:
    """What the server reports on ``hl/v1/status``.

    Attributes
    ----------
    online : tuple of str
        Devices holding a liveliness token, sorted.
    counts : Mapping[str, int]
        Messages by kind and rejections (``rejected:<reason>``) since the server started.
    db : Mapping[str, Any]
        The database's counts (devices, batches, steps, scans, marks, fixes), stored rejections by
        reason and newest map version per site (:meth:`hybridloc.server.store.Store.status`).
    maps_loaded : Mapping[str, int]
        Site -> version of the radio map the server locates with.
    slam : Mapping[str, Mapping[str, Any]]
        Site -> the crowd SLAM's figures (walks_corrected, walks_quarantined, walks_pending,
        loops_accepted, loops_rejected, coverage, map_version, ...: the server fills it). On the wire
        only when not empty: older servers send none, and their payloads decode with ``{}``.
    sites : tuple of str
        The sites this server process serves (``serve --site``); empty: every site. On the wire only
        when not empty. Several processes on one mesh each answer ``hl/v1/status``.
    rejections : Mapping[str, Mapping[str, int]]
        Device -> reason -> messages refused (stored counts, since the database began; ``?`` for
        messages on keys that name no device). On the wire only when not empty: older servers send
        none, and their payloads decode with ``{}``.
    """

    online: tuple[str, ...] = ()
    counts: Mapping[str, int] = field(default_factory=dict)
    db: Mapping[str, Any] = field(default_factory=dict)
    maps_loaded: Mapping[str, int] = field(default_factory=dict)
    slam: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    sites: tuple[str, ...] = ()
    rejections: Mapping[str, Mapping[str, int]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "online", tuple(self.online))
        object.__setattr__(self, "sites", tuple(self.sites))

    def as_dict(self) -> dict:
        """The message as a plain dict (what ``hybridloc status`` reads), without the schema."""
        return {
            "online": list(self.online),
            "counts": dict(self.counts),
            "db": dict(self.db),
            "maps_loaded": dict(self.maps_loaded),
            "slam": {site: dict(v) for site, v in self.slam.items()},
            "sites": list(self.sites),
            "rejections": {device: dict(v) for device, v in self.rejections.items()},
        }


@dataclass(frozen=True)
class MapInfo:
    """The attachment of a ``map`` reply (whose payload is the radio map file, npz bytes)."""

    site: str
    version: int


#: Where a radio map version came from: the crowd SLAM, a survey rebuild, a map file imported.
MAP_SOURCES = ("slam", "survey", "import")


@dataclass(frozen=True, eq=False)
class Track:
    """The crowd SLAM's corrected track of a device's walk, sent on the device's ``track`` key.

    Attributes
    ----------
    site, device : str
        Ids (:func:`~.protocol.check_id`).
    walk_id : int
        The server's id of the walk (>= 1). The device learns its walk's id only from these messages.
    map_version : int or None
        The radio map version the solve used (None: none).
    run : int
        The server's SLAM run that made the track (>= 1): a newer run supersedes an older one.
    track : CorrectedTrack
        The track; its ``walk_id`` is ``walk_id`` (filled in when None). On the wire: the newest
        :data:`~.protocol.MAX_TRACK_POINTS` points, covariances by their upper triangle.
    sent_at : float
        When the server sent it, s (Unix time on the server; 0 when unknown).
    """

    site: str
    device: str
    walk_id: int
    map_version: int | None
    run: int
    track: CorrectedTrack
    sent_at: float = 0.0

    def __post_init__(self) -> None:
        if self.track.walk_id is None:
            object.__setattr__(self, "track", dataclasses.replace(self.track, walk_id=self.walk_id))
        elif self.track.walk_id != self.walk_id:
            raise ValueError(f"Track: walk {self.walk_id} carries the track of walk {self.track.walk_id}")


@dataclass(frozen=True)
class MapVersion:
    """A new radio map version of a site, announced on ``hl/v1/<site>/map/version``.

    Attributes
    ----------
    site : str
    version : int
        The version (>= 1); a client holding an older one fetches the map (get on ``map``).
    source : str
        One of :data:`MAP_SOURCES`.
    created_at : float
        When the version was made, Unix time s (the server's clock).
    walks : int
        Walks whose scans the map was built from.
    coverage : float or None
        Share of the site's crowd scans (walks without survey marks) with an absolute corrected
        position, in [0, 1]; None when unknown (no crowd walk yet).
    """

    site: str
    version: int
    source: str
    created_at: float
    walks: int = 0
    coverage: float | None = None


@dataclass(frozen=True)
class Progress:
    """A running SLAM job's progress, on ``hl/v1/<site>/progress``.

    Attributes
    ----------
    site : str
    stage : str
        What the job is doing (the server's stage names, at most 32 characters).
    floor : str
        The floor being worked on ("" for the whole site), at most 32 characters.
    done, total : int
        Units of the stage done so far and in all, 0 <= done <= total.
    t : float
        When, Unix time s (the server's clock).
    """

    site: str
    stage: str
    floor: str
    done: int
    total: int
    t: float
