"""Shared by the SLAM worker tests: the bundled real sample as stored walks, and the child-process hook.

The bundled sample (Indoor Location Competition site1, floor F1, 35 real walks) has one floor; a batch
run checkpoints floor by floor, so the tests that kill a run midway split it in two: F2 is a copy of
F1's plan (same walls, level 1) and every other walk is stored as walked there. Each floor is then a
real crowd of 17-18 real walks, solved apart.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import numpy as np

from hybridloc.io.msft import find_ilc_traces, read_ilc_site
from hybridloc.samples import ILC_SITE1_F1
from hybridloc.types import AbsoluteFix, FloorPlan, StepEvent, SurveyMark, Walk
from hybridloc.wire.messages import Batch

#: the sample's site id (what its traces name)
SITE = "5dd3d7732a57a34356595932"


def sample_plan(two_floors: bool = False, n_floors: int | None = None) -> FloorPlan:
    """The sample's plan; with ``two_floors`` (or ``n_floors``) F1's copied as F2 (F3...), one level each."""
    plan = read_ilc_site(ILC_SITE1_F1)
    n = n_floors or (2 if two_floors else 1)
    floors = (plan.floors[0],) + tuple(dataclasses.replace(plan.floors[0], name=f"F{k + 1}", level=k) for k in range(1, n))
    return FloorPlan(SITE, floors, (), plan.origin)


def sample_walks(marks_every: int = 3) -> list[Walk]:
    """The 35 sample walks through the phone PDR; walks 0, k, 2k... keep their survey marks."""
    from hybridloc.slam.walkgraph import walks_from_files

    paths = find_ilc_traces(ILC_SITE1_F1)
    return [w for w, _ in walks_from_files(paths, marks=[i % marks_every == 0 for i in range(len(paths))], workers=2)]


def floor_of(i: int, two_floors: bool, floors: tuple[str, ...] | None = None) -> str:
    if floors:
        return floors[i % len(floors)]
    return "F2" if two_floors and i % 2 else "F1"


def store_walks(
    store, walks: list[Walk], two_floors: bool = False, prefix: str = "dev", floors: tuple[str, ...] | None = None, ended: bool = True
) -> list[str]:
    """Each walk as one device's ended walk (batches of at most 500 records, the last with the end-of-walk
    marker; with ``ended`` False none: the walk is still open); a walk without marks names its floor
    through a fix, as the server does when it answers a scan. Walk i is on ``floors[i % len(floors)]``
    (default F1, or F1 / F2 alternately with ``two_floors``). Returns the device ids."""
    devices = []
    for i, w in enumerate(walks):
        dev = f"{prefix}{i:02d}"
        fl = floor_of(i, two_floors, floors)
        recs = [("s", r) for r in w.steps] + [("c", r) for r in w.scans] + [("m", SurveyMark(r.t, r.x, r.y, fl)) for r in w.marks]
        recs.sort(key=lambda x: x[1].t)
        chunks = [recs[k : k + 500] for k in range(0, len(recs), 500)] or [[]]
        batches = []
        for seq, ch in enumerate(chunks, 1):
            batches.append(
                Batch(
                    SITE,
                    dev,
                    seq,
                    w.device_model,
                    [r for k, r in ch if k == "s"],
                    [r for k, r in ch if k == "c"],
                    [r for k, r in ch if k == "m"],
                    end_of_walk=ended and seq == len(chunks),
                )
            )
        store.persist(batches)
        if not w.marks and w.scans:
            store.add_fixes([(dev, AbsoluteFix(w.scans[0].t, np.zeros(2), np.eye(2), "wifi", fl))])
        devices.append(dev)
    return devices


def crossing_walk(a: Walk, b: Walk, gap_s: float = 5.0) -> Walk:
    """Walk ``a``, then ``gap_s`` later walk ``b`` one floor up (its first step a floor change): one walk
    on two floors, as a walker taking the stairs gives. Neither may have marks (they name one floor)."""
    assert not a.marks and not b.marks
    dt = a.t_end + gap_s - b.t_start
    steps_b = [dataclasses.replace(s, t=s.t + dt) for s in b.steps]
    steps_b[0] = dataclasses.replace(steps_b[0], floor_change=1)
    scans_b = [dataclasses.replace(c, t=c.t + dt) for c in b.scans]
    return dataclasses.replace(a, t_end=b.t_end + dt, steps=a.steps + tuple(steps_b), scans=a.scans + tuple(scans_b))


def stretched(walk: Walk, factor: float) -> Walk:
    """The walk with every step ``factor`` times as long (10 m steps: no person walks so)."""
    steps = tuple(dataclasses.replace(s, length=s.length * factor) for s in walk.steps)
    return dataclasses.replace(walk, steps=steps)


def straight_steps(n: int, t0: float, length: float = 0.7) -> list[StepEvent]:
    return [StepEvent(t0 + 0.5 * i, length, 0.0, 0.05, 0.1) for i in range(n)]


# ------------------------------------------------------------------------------------------ child hook
def hook(event: str, site: str, subject, arg: str) -> None:
    """The SLAM child's test hook (``SlamOptions.child_hook = "tests.slam_helpers:hook"``), driven by
    files in the folder ``arg`` so a test steers it from outside the child:

    * walk of device D: ``D.block`` -> write ``D.entered`` and wait until ``D.release`` exists;
      ``D.raise`` -> raise RuntimeError; ``D.crash`` -> the child process dies (os._exit);
    * floor F of a batch run: ``floor-F.block`` -> write ``floor-F.entered``, wait for ``floor-F.release``.
    """
    d = Path(arg)
    name = subject.device if event == "walk" else f"floor-{subject}"
    if (d / f"{name}.crash").exists():
        os._exit(3)
    if (d / f"{name}.raise").exists():
        raise RuntimeError(f"test hook: the solve of {name} fails")
    if (d / f"{name}.block").exists():
        (d / f"{name}.entered").write_text(str(os.getpid()))
        while not (d / f"{name}.release").exists():
            time.sleep(0.05)


def store_three_floors_with_stairs(st) -> str:
    """Fill the :class:`~hybridloc.server.store.Store` ``st``: three floors (F2, F3 copies of F1's plan),
    9 sample walks on them (every third one keeping its marks), and one more walk made of two unmarked
    sample walks, the second one floor up (a walker taking the stairs: its first scan upstairs gets a fix
    naming F2). F1 and F2 are then one connected group of floors, F3 another. Returns the stairs device."""
    walks = sample_walks()
    st.save_floor_plan(SITE, sample_plan(n_floors=3))
    store_walks(st, walks[:9], floors=("F1", "F2", "F3"))
    cross = crossing_walk(walks[13], walks[14])
    (dev,) = store_walks(st, [cross], prefix="stairs", floors=("F1",))
    t_up = cross.scans[len(walks[13].scans)].t  # the first scan upstairs names F2
    st.add_fixes([(dev, AbsoluteFix(t_up, np.zeros(2), np.eye(2), "wifi", "F2"))])
    return dev
