"""``hybridloc map show``: coverage and one transmitter's heat map per floor, as a PNG (matplotlib)."""

from __future__ import annotations

import numpy as np

from .radiomap import RadioMap


def plot_map(map_path: str, out_png: str, tx: str | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
        for ax in row:
            ax.set_aspect("equal")
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
    fig.tight_layout()
    fig.savefig(out_png, dpi=80)
    plt.close(fig)
