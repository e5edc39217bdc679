"""``hybridloc map show``: coverage and one transmitter's heat map per floor, as a PNG (matplotlib),
over the floor plan's walls when one is given."""

from __future__ import annotations

import numpy as np

from ..types import FloorPlan
from .radiomap import RadioMap


def plot_map(map_path: str, out_png: str, tx: str | None = None, plan: FloorPlan | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    rmap = RadioMap.load(map_path)
    floors = list(rmap.floors.values())
    if tx is None:  # the transmitter seen on the most cells, summed over floors
        seen = np.zeros(len(rmap.transmitters))
        for f in floors:
            seen[f.tx] += (f.pd > 0.5).sum(axis=0)
        tx = rmap.transmitters[int(np.argmax(seen))]
    j = rmap.tx_index.get(tx)
    if j is None:
        raise ValueError(f"transmitter {tx!r} is not in the map")
    fig, axes = plt.subplots(len(floors), 2, figsize=(12, 5 * len(floors)), squeeze=False)
    for row, f in zip(axes, floors):
        s = row[0].scatter(f.cells[:, 0], f.cells[:, 1], c=np.log1p(f.support), s=4, marker="s", cmap="viridis")
        row[0].set_title(f"{f.name}: coverage (log(1 + effective scans))")
        fig.colorbar(s, ax=row[0])
        cols = np.flatnonzero(f.tx == j)
        if cols.size:
            c = cols[0]
            vals = np.where(f.pd[:, c] > 0.1, f.mu[:, c], np.nan)
            s2 = row[1].scatter(f.cells[:, 0], f.cells[:, 1], c=vals, s=4, marker="s", cmap="inferno", vmin=-100, vmax=-30)
            fig.colorbar(s2, ax=row[1], label="mean RSSI, dBm")
        row[1].set_title(f"{f.name}: {tx}")
        walls, rooms = _plan_lines(plan, f.name)
        for ax in row:
            if rooms:
                ax.add_collection(LineCollection(rooms, colors="0.8", linewidths=0.5, zorder=0))
            if walls is not None:
                ax.add_collection(LineCollection(walls, colors="0.45", linewidths=0.7, zorder=0))
            ax.set_aspect("equal")
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
    fig.tight_layout()
    fig.savefig(out_png, dpi=80)
    plt.close(fig)


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
