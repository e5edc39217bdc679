"""The ``hybridloc sim world`` / ``sim walk`` jobs (library side: no argument parsing here)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .building import World, generate_world, world_from_plan
from .imu import disturbance_field, foot_imu, phone_sensors
from .output import write_foot_csv, write_ilc_trace, write_truth, write_world
from .radio import make_radio_model, simulate_radio
from .walker import simulate_walk


def make_world(seed: int, floors: int, out: str, floorplan: str | None = None) -> World:
    """A generated building of ``floors`` floors, or - with ``floorplan`` (a site folder in the Indoor
    Location Competition layout) - a world on that real plan (:func:`.building.world_from_plan`)."""
    if floorplan:
        from ..io.msft import read_ilc_site

        src = str(Path(floorplan).resolve())
        world = world_from_plan(read_ilc_site(src), np.random.default_rng(seed), seed, source=src)
    else:
        world = generate_world(np.random.default_rng(seed), floors, seed)
    write_world(world, out)
    return world


def load_world(folder: str) -> World:
    p = Path(folder) / "world.json"
    try:
        meta = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ValueError(f"{folder}: not a simulated world folder ({exc})") from exc
    if meta.get("format") != "hybridloc-sim-world":
        raise ValueError(f"{p}: not a hybridloc simulated world")
    if meta.get("floorplan"):  # a world on a real plan: regenerated from the plan it names
        from ..io.msft import read_ilc_site

        src = meta["floorplan"]
        if not Path(src).is_dir():
            raise ValueError(f"{p}: the floor plan folder it was made from, {src}, is gone")
        world = world_from_plan(read_ilc_site(src), np.random.default_rng(int(meta["seed"])), int(meta["seed"]), source=src)
    else:
        world = generate_world(np.random.default_rng(int(meta["seed"])), int(meta["floors"]), int(meta["seed"]))
    if len(world.aps) != len(meta["aps"]) or abs(world.width - meta["width"]) > 1e-9:
        raise ValueError(f"{p}: the world was made by another hybridloc version (regenerated layout differs)")
    return world


def simulate_walks(world: World, walkers: int, minutes: float, carrier: str, out: str, seed: int = 0, progress=None) -> list[Path]:
    if carrier not in ("phone", "foot", "both"):
        raise ValueError("carrier must be phone, foot or both")
    if walkers < 1 or minutes <= 0:
        raise ValueError("need at least one walker and a positive duration")
    out_p = Path(out)
    out_p.mkdir(parents=True, exist_ok=True)
    root = np.random.default_rng([seed, world.seed])
    model = make_radio_model(world, np.random.default_rng([world.seed, 7]))
    field = disturbance_field(np.random.default_rng([world.seed, 11]))
    written = []
    for i in range(walkers):
        rng = np.random.default_rng(root.integers(2**63))
        walk = simulate_walk(world, rng, minutes, walker=i, t0=1.7e9 + 3600.0 * i)
        prefix = out_p / f"w{i:04d}"
        foot_truth = None
        radio = None
        device = ["SIM PHONE-A", "SIM PHONE-B", "SIM PHONE-C"][i % 3]
        offset = [0.0, -4.0, 3.0][i % 3]
        if carrier in ("phone", "both"):
            phone = phone_sensors(walk, rng, mag_field=field)
            radio = simulate_radio(model, walk, rng, device, offset)
            write_ilc_trace(f"{prefix}.txt.gz", world, walk, phone.imu, radio, device, phone.rotation_vector)
        if carrier in ("foot", "both"):
            fimu, foot_truth = foot_imu(walk, rng)
            write_foot_csv(prefix, fimu)
        write_truth(prefix, walk, radio, foot_truth, world)
        written.append(prefix)
        if progress:
            progress(i + 1, walkers)
    return written
