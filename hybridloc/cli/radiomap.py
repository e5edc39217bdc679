"""``hybridloc map build`` and ``hybridloc map show``: radio map files."""

from __future__ import annotations

import argparse

from ..errors import BadInput, MissingData


def _cmd_map_build(args: argparse.Namespace) -> int:
    from ..radio.radiomap import BuildParams, build_radio_map
    from ..radio.sources import labelled_from_inputs

    if args.reach is not None and not args.reach > 0:
        raise BadInput(f"--reach must be a positive distance in metres, not {args.reach}")
    if args.reach is not None and args.prior != "path-loss":
        raise BadInput("--reach needs --prior path-loss (past the kernel's reach only the model has anything to say)")
    labelled, plan, site = labelled_from_inputs(args.format, args.inputs, args.floorplan)
    if not labelled:
        raise MissingData("no labelled scans in the inputs (surveys need at least two waypoints)")
    params = BuildParams(cell=args.cell, max_age_s=args.max_age, prior=args.prior, reach_m=args.reach)
    rmap = build_radio_map(labelled, site=args.site or site, plan=plan, params=params)
    rmap.save(args.out)
    fl = ", ".join(f"{f.name}: {len(f.cells)} cells, {len(f.tx)} transmitters" for f in rmap.floors.values())
    print(f"radio map of {len(labelled)} labelled scans -> {args.out} ({fl}; device offsets {rmap.device_offsets})")
    return 0


def _cmd_map_show(args: argparse.Namespace) -> int:
    from ..radio.plot import plot_map
    from ..radio.radiomap import RadioMap
    from ._common import pyplot

    plan = None
    if args.floorplan:
        from ..io.msft import read_ilc_site

        plan = read_ilc_site(args.floorplan)
    rmap = RadioMap.load(args.map)
    plt = pyplot("map show")
    fig, axes = plt.subplots(len(rmap.floors), 2, figsize=(12, 5 * len(rmap.floors)), squeeze=False)
    try:
        plot_map(axes, rmap, args.tx, plan)
        fig.tight_layout()
        fig.savefig(args.out, dpi=80)
    finally:
        plt.close(fig)
    print(f"wrote {args.out}")
    return 0


def register(msub) -> None:
    mb = msub.add_parser("build", help="build a radio map from surveys (waypointed traces) or labelled fingerprints")
    mb.add_argument("inputs", nargs="+", metavar="INPUT")
    mb.add_argument("--format", choices=("msft", "ujiindoorloc", "csv"), required=True)
    mb.add_argument("--floorplan", help="site folder or geojson_map.json of the floor plan (msft; found next to the traces by default)")
    mb.add_argument("--out", required=True, metavar="MAP", help="radio map file (.npz)")
    mb.add_argument("--site", help="site name stored in the map")
    mb.add_argument("--cell", type=float, default=1.5, help="grid cell size, m (default 1.5)")
    mb.add_argument("--max-age", type=float, default=8.0, help="leave out readings older than this at scan time, s (default 8)")
    mb.add_argument(
        "--prior",
        choices=("floor-mean", "path-loss"),  # radio.radiomap.PRIORS, not imported here: the CLI starts without shapely and scipy
        default="floor-mean",
        help="where the labels are thin: each transmitter's floor-wide mean (default), or a log-distance path-loss model fitted per "
        "transmitter (the cell likelihood 27 %% closer on ILC site1, the kNN answer unchanged: eval fingerprint)",
    )
    mb.add_argument(
        "--reach", type=float, help="keep cells within this distance of a labelled scan, m (default: the kernel's reach, 3 bandwidths + a cell)"
    )
    mb.set_defaults(func=_cmd_map_build)
    ms = msub.add_parser("show", help="coverage and per-transmitter heat maps as a PNG")
    ms.add_argument("map", metavar="MAP")
    ms.add_argument("--out", required=True, metavar="PNG")
    ms.add_argument("--tx", help="transmitter to draw (default: the most widely seen)")
    ms.add_argument(
        "--floorplan",
        metavar="GEOJSON",
        help="floor plan to draw under the maps: a site folder (Indoor Location Competition layout) or a simulated world's folder, as for map build",
    )
    ms.set_defaults(func=_cmd_map_show)
