"""Records that exist only on the wire: the batch (the unit of delivery), its acknowledgement, the
locate request, the server's status and the radio map's attachment.

The records every layer shares (:class:`~hybridloc.types.StepEvent`, :class:`~hybridloc.types.RfScan`,
:class:`~hybridloc.types.SurveyMark`, :class:`~hybridloc.types.Fix`, :class:`~hybridloc.types.Pose`)
live in :mod:`hybridloc.types`; :mod:`.codecs` turns all of them into bytes and back.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..types import RfScan, StepEvent, SurveyMark


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
    sent_at : float
        When the client sent the batch, s (Unix time on the client; 0 when unknown).
    end_of_walk : bool
        The device's walk ends with this batch (its replay or live input ended): the server closes the
        walk at once instead of after the idle gap. On the wire only when true (older clients omit it).
    """

    site: str
    device: str
    seq: int
    device_model: str = ""
    steps: tuple[StepEvent, ...] = ()
    scans: tuple[RfScan, ...] = ()
    marks: tuple[SurveyMark, ...] = ()
    sent_at: float = 0.0
    end_of_walk: bool = False

    def __post_init__(self) -> None:
        for name in ("steps", "scans", "marks"):
            object.__setattr__(self, name, tuple(getattr(self, name)))

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
    """

    online: tuple[str, ...] = ()
    counts: Mapping[str, int] = field(default_factory=dict)
    db: Mapping[str, Any] = field(default_factory=dict)
    maps_loaded: Mapping[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "online", tuple(self.online))

    def as_dict(self) -> dict:
        """The message as a plain dict (what ``hybridloc status`` reads), without the schema."""
        return {"online": list(self.online), "counts": dict(self.counts), "db": dict(self.db), "maps_loaded": dict(self.maps_loaded)}


@dataclass(frozen=True)
class MapInfo:
    """The attachment of a ``map`` reply (whose payload is the radio map file, npz bytes)."""

    site: str
    version: int
