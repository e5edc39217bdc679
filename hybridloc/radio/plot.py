"""Radio map figures (``hybridloc map show``): coverage and one transmitter's heat map per floor,
over the floor plan's walls when one is given. Every function draws into the matplotlib ``ax`` it is
given (the caller makes and saves the figure), as evo's plot functions do."""

from __future__ import annotations

import numpy as np

from ..types import FloorPlan
from .radiomap import RadioMap


def most_seen_transmitter(rmap: RadioMap) -> str:
    """The transmitter seen on the most cells (detection probability > 0.5), summed over floors."""
    seen = np.zeros(len(rmap.transmitters))
    for f in rmap.floors.values():
        seen[f.tx] += (f.pd > 0.5).sum(axis=0)
    return rmap.transmitters[int(np.argmax(seen))]


def plot_coverage(ax, floor):
    """Cells coloured by log(1 + effective scans); returns the mappable (for a colour bar)."""
    s = ax.scatter(floor.cells[:, 0], floor.cells[:, 1], c=np.log1p(floor.support), s=4, marker="s", cmap="viridis")
    ax.set_title(f"{floor.name}: coverage (log(1 + effective scans))")
    return s


def plot_transmitter(ax, floor, j: int, tx: str):
    """Mean RSSI (dBm) of transmitter column ``j`` where it is heard (detection probability > 0.1);
    returns the mappable, or None when the floor never hears it."""
    cols = np.flatnonzero(floor.tx == j)
    s2 = None
    if cols.size:
        c = cols[0]
        vals = np.where(floor.pd[:, c] > 0.1, floor.mu[:, c], np.nan)
        s2 = ax.scatter(floor.cells[:, 0], floor.cells[:, 1], c=vals, s=4, marker="s", cmap="inferno", vmin=-100, vmax=-30)
    ax.set_title(f"{floor.name}: {tx}")
    return s2


def plot_plan(ax, plan: FloorPlan | None, floor: str) -> None:
    """The floor's rooms (light) and walls under what is drawn, equal axes in metres."""
    from matplotlib.collections import LineCollection

    walls, rooms = _plan_lines(plan, floor)
    if rooms:
        ax.add_collection(LineCollection(rooms, colors="0.8", linewidths=0.5, zorder=0))
    if walls is not None:
        ax.add_collection(LineCollection(walls, colors="0.45", linewidths=0.7, zorder=0))
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def plot_map(axes, rmap: RadioMap, tx: str | None = None, plan: FloorPlan | None = None) -> str:
    """Per floor of ``rmap``, one row of ``axes`` (shape (floors, 2)): coverage, and transmitter
    ``tx`` (default :func:`most_seen_transmitter`), each with its colour bar. Returns the transmitter."""
    from ..errors import BadInput

    floors = list(rmap.floors.values())
    if tx is None:
        tx = most_seen_transmitter(rmap)
    j = rmap.tx_index.get(tx)
    if j is None:
        raise BadInput(f"transmitter {tx!r} is not in the map")
    for row, f in zip(axes, floors):
        fig = row[0].figure
        fig.colorbar(plot_coverage(row[0], f), ax=row[0])
        s2 = plot_transmitter(row[1], f, j, tx)
        if s2 is not None:
            fig.colorbar(s2, ax=row[1], label="mean RSSI, dBm")
        for ax in row:
            plot_plan(ax, plan, f.name)
    return tx


def _plan_lines(plan: FloorPlan | None, floor: str) -> tuple[np.ndarray | None, list[np.ndarray]]:
    """The floor's wall segments (M, 2, 2) and its rooms' outlines (shops, offices: lighter), or
    (None, []) without a plan or that floor in it."""
    if plan is None:
        return None, []
    try:
        fl = plan.floor(floor)
    except KeyError:
        return None, []
    w = np.asarray(fl.walls, float)
    rooms = [np.asarray(poly.exterior.coords) for _, poly in fl.rooms if not poly.is_empty]
    return (w if w.size else None), rooms
