"""Generated buildings: multi-floor office-like layouts as a :class:`~hybridloc.types.FloorPlan` plus the
walkable graph walkers route on, and the radio infrastructure (WiFi APs, BLE beacons, RFID readers).

Layout of every floor (site frame, metres, origin at the building's south-west corner):

* a central east-west corridor (``corridor_width`` wide) along the building;
* rooms on both sides, 4-8 m wide, each with a 1 m door onto the corridor;
* a stairwell at the west end and a lift at the east end joining consecutive floors;
* a main entrance in the middle of the south facade on the ground floor, with an outdoor forecourt
  (where GPS works) in front of it.

Every function takes an explicit ``numpy.random.Generator``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from shapely.geometry import MultiPolygon, Polygon, box

from ..geo import GeodeticOrigin
from ..types import Floor, FloorPlan, FloorTransition, TransitionKind

STOREY = 3.5  # m


@dataclass
class Room:
    floor: int
    name: str
    poly: Polygon
    door: tuple[float, float]  # door centre on the corridor wall
    centre: tuple[float, float]


@dataclass
class World:
    """A generated building with its infrastructure."""

    seed: int
    plan: FloorPlan
    width: float
    depth: float
    corridor_y: tuple[float, float]
    rooms: list[Room]
    nodes: np.ndarray  # (K, 3) walkable graph nodes: x, y, floor index
    node_kind: list[str]
    edges: list[tuple[int, int]]
    aps: np.ndarray  # (A, 3) x, y, floor index
    ap_ids: list[str]
    ap_freq_mhz: np.ndarray
    beacons: np.ndarray  # (B, 3)
    beacon_ids: list[str]
    rfid: np.ndarray  # (R, 3) readers at doors
    entrance: tuple[float, float]
    outdoor_node: int
    origin: GeodeticOrigin
    _dist: np.ndarray | None = field(default=None, repr=False)
    _pred: np.ndarray | None = field(default=None, repr=False)
    #: lower-left corner of the building's bounding box (generated buildings start at the origin)
    x_min: float = 0.0
    y_min: float = 0.0
    #: the real floor plan folder the world was made from (None: generated)
    source: str | None = None
    _comp: np.ndarray | None = field(default=None, repr=False)

    @property
    def n_floors(self) -> int:
        return len(self.plan.floors)

    def floor_name(self, i: int) -> str:
        return self.plan.floors[i].name

    @property
    def component(self) -> np.ndarray:
        """Connected component of every graph node (a real plan without stairs data has one per floor)."""
        if self._comp is None:
            self._comp = graph_components(len(self.nodes), self.edges)
        return self._comp

    def inside(self, pos: np.ndarray) -> np.ndarray:
        """Which positions (N, 2) lie inside the ground floor's outline."""
        return shapely.contains_xy(self.plan.floors[0].outline, pos[:, 0], pos[:, 1])

    def shortest_path(self, a: int, b: int) -> list[int]:
        if self._dist is None:
            n = len(self.nodes)
            w = [
                float(np.linalg.norm(self.nodes[i, :2] - self.nodes[j, :2])) + (STOREY * 2 if self.nodes[i, 2] != self.nodes[j, 2] else 0.0)
                for i, j in self.edges
            ]
            rows = [i for i, _ in self.edges] + [j for _, j in self.edges]
            cols = [j for _, j in self.edges] + [i for i, _ in self.edges]
            g = csr_matrix((w + w, (rows, cols)), shape=(n, n))
            self._dist, self._pred = dijkstra(g, directed=False, return_predecessors=True)
        path = [b]
        while path[-1] != a:
            p = int(self._pred[a, path[-1]])
            if p < 0:
                raise ValueError(f"no path between nodes {a} and {b}")
            path.append(p)
        return path[::-1]


def generate_world(
    rng: np.random.Generator,
    floors: int = 3,
    seed: int = 0,
    width: float | None = None,
    depth: float | None = None,
    origin: GeodeticOrigin | None = None,
) -> World:
    if not 1 <= floors <= 50:
        raise ValueError("floors must be between 1 and 50")
    W = float(width if width is not None else rng.uniform(50.0, 80.0))
    D = float(depth if depth is not None else rng.uniform(20.0, 26.0))
    cw = 2.5
    cy0, cy1 = D / 2 - cw / 2, D / 2 + cw / 2
    stair_w, lift_w = 4.0, 3.0
    origin = origin or GeodeticOrigin.from_degrees(47.3769, 8.5417, 410.0)
    # room partitions, shared by every floor (a building's structure repeats)
    xs_n, xs_s = [stair_w], [stair_w]
    for xs in (xs_n, xs_s):
        while xs[-1] < W - lift_w - 4.0:
            xs.append(min(xs[-1] + float(rng.uniform(4.0, 8.0)), W - lift_w))
        xs[-1] = W - lift_w
    fl_objs, rooms, transitions = [], [], []
    nodes: list[tuple[float, float, int]] = []
    kinds: list[str] = []
    edges: list[tuple[int, int]] = []
    rfid = []
    stair_nodes, lift_nodes = [], []
    entrance = (W / 2, 0.0)

    def add(x, y, f, kind):
        nodes.append((x, y, f))
        kinds.append(kind)
        return len(nodes) - 1

    for f in range(floors):
        walls = [((0, 0), (W, 0)), ((W, 0), (W, D)), ((W, D), (0, D)), ((0, D), (0, 0))]
        fl_rooms = []
        # corridor nodes every ~2 m
        cx = np.linspace(1.0, W - 1.0, max(3, int(W / 2.0)))
        cn = [add(float(x), D / 2, f, "corridor") for x in cx]
        edges += list(zip(cn[:-1], cn[1:]))
        for side, xs, (y0, y1), wall_y in (("N", xs_n, (cy1, D), cy1), ("S", xs_s, (0.0, cy0), cy0)):
            gaps = []
            for k in range(len(xs) - 1):
                x0, x1 = xs[k], xs[k + 1]
                door_x = float(rng.uniform(x0 + 1.0, x1 - 1.0))
                gaps.append((door_x - 0.5, door_x + 0.5))
                walls.append(((x1, y0), (x1, y1)))  # partition to the next room
                poly = box(x0, y0, x1, y1)
                name = f"{f + 1}{side}{k + 1:02d}"
                centre = ((x0 + x1) / 2, (y0 + y1) / 2)
                room = Room(f, name, poly, (door_x, wall_y), centre)
                fl_rooms.append(room)
                # graph: corridor node nearest the door -> door -> room centre
                ci = cn[int(np.argmin(np.abs(cx - door_x)))]
                dn = add(door_x, wall_y, f, "door")
                rn = add(centre[0], centre[1], f, "room")
                edges += [(ci, dn), (dn, rn)]
                rfid.append((door_x, wall_y, f))
            if f == 0 and side == "S":  # the entrance link crosses the south rooms to the corridor
                gaps.append((W / 2 - 1.0, W / 2 + 1.0))
            # the corridor wall on this side, with door gaps
            x = stair_w
            for g0, g1 in sorted(gaps):  # overlapping gaps (a door in the entrance's) merge
                if g0 > x:
                    walls.append(((x, wall_y), (g0, wall_y)))
                x = max(x, g1)
            walls.append(((x, wall_y), (W - lift_w, wall_y)))
        # stairwell (west) and lift (east) ends are open to the corridor
        sn = add(stair_w / 2, D / 2, f, "stairs")
        ln = add(W - lift_w / 2, D / 2, f, "lift")
        edges += [(sn, cn[0]), (ln, cn[-1])]
        stair_nodes.append(sn)
        lift_nodes.append(ln)
        rooms += fl_rooms
        outline = MultiPolygon([box(0, 0, W, D)])
        # the entrance gap in the south facade on the ground floor
        if f == 0:
            walls[0] = ((0, 0), (W / 2 - 1.0, 0))
            walls.append(((W / 2 + 1.0, 0), (W, 0)))
        fl_objs.append(Floor(f"F{f + 1}", f, f * STOREY, outline, outline, np.array(walls, float), tuple((r.name, r.poly) for r in fl_rooms)))
    for f in range(floors - 1):
        edges += [(stair_nodes[f], stair_nodes[f + 1]), (lift_nodes[f], lift_nodes[f + 1])]
        transitions += [
            FloorTransition(TransitionKind.STAIRS, f"F{f + 1}", f"F{f + 2}", (stair_w / 2, D / 2), (stair_w / 2, D / 2)),
            FloorTransition(TransitionKind.LIFT, f"F{f + 1}", f"F{f + 2}", (W - lift_w / 2, D / 2), (W - lift_w / 2, D / 2)),
        ]
    # entrance: a south-room-free corridor link through the facade, and the outdoor forecourt
    ent_in = add(W / 2, D / 2, 0, "corridor")
    ent_door = add(W / 2, 0.0, 0, "entrance")
    outdoor = add(W / 2, -12.0, 0, "outdoor")
    near = [i for i, k in enumerate(kinds) if k == "corridor" and nodes[i][2] == 0]
    nearest = min(near, key=lambda i: abs(nodes[i][0] - W / 2) if i != ent_in else 1e9)
    edges += [(ent_in, nearest), (ent_in, ent_door), (ent_door, outdoor)]
    rfid.append((W / 2, 0.0, 0))
    # the south room under the entrance corridor is now a lobby: the corridor wall is open where the
    # link meets it (the gap added with the doors above)
    plan = FloorPlan(f"sim-{seed}", tuple(fl_objs), tuple(transitions), origin)
    # WiFi access points: ceiling-mounted along the corridor every ~15 m, alternate floors staggered
    aps, ap_ids, freqs = [], [], []
    for f in range(floors):
        n_ap = max(2, int(round(W / 15.0)))
        xs = (np.arange(n_ap) + 0.5 + (0.5 if f % 2 else 0.0)) * W / n_ap
        for x in xs:
            for _band, fmhz in (("2g", 2437.0), ("5g", 5180.0)):  # one AP id per band at the same place
                aps.append((float(min(x, W - 0.5)), D / 2 + float(rng.uniform(-1, 1)), f))
                ap_ids.append(f"02:00:{seed % 256:02x}:{f:02x}:{len(ap_ids) // 256 % 256:02x}:{len(ap_ids) % 256:02x}")
                freqs.append(fmhz)
    # BLE beacons every ~8 m in the corridor, and one per room
    beacons, beacon_ids = [], []
    for f in range(floors):
        for x in np.arange(4.0, W - 2.0, 8.0):
            beacons.append((float(x), D / 2, f))
        for r in rooms:
            if r.floor == f:
                beacons.append((r.centre[0], r.centre[1], f))
    beacon_ids = [f"sim{seed}_{i // 1000}_{i % 1000}" for i in range(len(beacons))]
    return World(
        seed,
        plan,
        W,
        D,
        (cy0, cy1),
        rooms,
        np.array(nodes, float),
        kinds,
        edges,
        np.array(aps, float),
        ap_ids,
        np.array(freqs),
        np.array(beacons, float),
        beacon_ids,
        np.array(rfid, float),
        entrance,
        outdoor,
        origin,
    )


def walkable_points(world: World, floor: int, pts: np.ndarray) -> np.ndarray:
    return shapely.contains_xy(world.plan.floors[floor].walkable, pts[:, 0], pts[:, 1])


def graph_components(n: int, edges: list[tuple[int, int]]) -> np.ndarray:
    """Connected-component label of each of ``n`` nodes of an undirected graph."""
    from scipy.sparse.csgraph import connected_components

    rows = [a for a, _ in edges]
    cols = [b for _, b in edges]
    return connected_components(csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False)[1]


def world_from_plan(
    plan: FloorPlan, rng: np.random.Generator, seed: int = 0, spacing: float = 2.0, origin: GeodeticOrigin | None = None, source: str | None = None
) -> World:
    """A simulated world on a real floor plan (e.g. an Indoor Location Competition site).

    Walkable graph: a grid of nodes every ``spacing`` m over each floor's free space - the walkable area
    minus its rooms (shops in those plans have no doors in the data, and the recorded walkers keep to
    the corridors), shrunk by 0.4 m so nobody brushes a wall - joined to their 8 neighbours where the
    straight link stays in the free space. Destinations ("room" nodes) are the shop fronts: the node
    nearest each room. Floors are joined where the plan has transitions (stairs, lifts); without them
    every floor is its own component and walkers stay on theirs. The entrance is the ground-floor point
    of the outline nearest the free space's centre-most boundary node, with an outdoor node 12 m out.
    Infrastructure is placed like real deployments: WiFi APs (2.4 and 5 GHz) every ~15 m and BLE
    beacons every ~8 m over the corridors (farthest-point spacing), RFID readers at the entrance and
    every fifth shop front.
    """
    from shapely.ops import unary_union

    origin = origin or plan.origin or GeodeticOrigin.from_degrees(47.3769, 8.5417, 410.0)
    nodes: list[tuple[float, float, int]] = []
    kinds: list[str] = []
    edges: list[tuple[int, int]] = []
    rooms: list[Room] = []
    rfid: list[tuple[float, float, int]] = []
    aps, ap_ids, freqs, beacons = [], [], [], []

    def add(x, y, f, kind):
        nodes.append((float(x), float(y), int(f)))
        kinds.append(kind)
        return len(nodes) - 1

    def spaced(pts: np.ndarray, d: float) -> np.ndarray:
        """Farthest-point sampling until every point is within d of a chosen one."""
        if len(pts) == 0:
            return pts
        chosen = [int(rng.integers(len(pts)))]
        dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
        while dist.max() > d:
            k = int(np.argmax(dist))
            chosen.append(k)
            dist = np.minimum(dist, np.linalg.norm(pts - pts[k], axis=1))
        return pts[chosen]

    floor_nodes: dict[int, np.ndarray] = {}
    for fi, fl in enumerate(plan.floors):
        free = fl.walkable
        if fl.rooms:
            free = free.difference(unary_union([r for _, r in fl.rooms]))
        free = free.buffer(-0.4)
        if free.is_empty:
            continue
        x0, y0, x1, y1 = free.bounds
        gx = np.arange(x0 + spacing / 2, x1, spacing)
        gy = np.arange(y0 + spacing / 2, y1, spacing)
        X, Y = np.meshgrid(gx, gy)
        ok = shapely.contains_xy(free, X, Y)
        ids = np.full(ok.shape, -1)
        for iy, ix in zip(*np.nonzero(ok)):
            ids[iy, ix] = add(X[iy, ix], Y[iy, ix], fi, "corridor")
        a_list, b_list = [], []
        ny, nx = ids.shape

        def shift(d: int, n: int) -> tuple[slice, slice]:
            return (slice(0, n - d), slice(d, n)) if d >= 0 else (slice(-d, n), slice(0, n + d))

        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):  # 8-neighbourhood, each link once
            (sy, ty), (sx, tx) = shift(dy, ny), shift(dx, nx)
            src, dst = ids[sy, sx], ids[ty, tx]
            m = (src >= 0) & (dst >= 0)
            a_list.append(src[m])
            b_list.append(dst[m])
        a_ids, b_ids = np.concatenate(a_list), np.concatenate(b_list)
        if len(a_ids):
            P = np.array(nodes, float)
            segs = shapely.linestrings(np.stack([P[a_ids, :2], P[b_ids, :2]], axis=1))
            keep = shapely.contains(free, segs)
            edges += list(zip(a_ids[keep].tolist(), b_ids[keep].tolist()))
        idx = np.nonzero(ids.ravel() >= 0)[0]
        fn = ids.ravel()[idx]
        floor_nodes[fi] = fn
        pts = np.array(nodes, float)[fn, :2]
        # shop fronts: the free-space node nearest each room is where walkers go
        if fl.rooms and len(pts):
            for name, poly in fl.rooms:
                d = shapely.distance(poly, shapely.points(pts))
                j = int(np.argmin(d))
                if d[j] > 3.0 * spacing:
                    continue
                kinds[int(fn[j])] = "room"
                c = poly.representative_point()
                rooms.append(Room(fi, str(name), poly, (float(pts[j, 0]), float(pts[j, 1])), (c.x, c.y)))
                if len(rooms) % 5 == 0:
                    rfid.append((float(pts[j, 0]), float(pts[j, 1]), fi))
        elif len(pts):  # no rooms in the plan: a fifth of the places are destinations
            for j in rng.choice(len(fn), max(1, len(fn) // 5), replace=False):
                kinds[int(fn[j])] = "room"
        for x, y in spaced(pts, 15.0):
            for fmhz in (2437.0, 5180.0):
                aps.append((float(x), float(y), fi))
                ap_ids.append(f"02:01:{seed % 256:02x}:{fi:02x}:{len(ap_ids) // 256 % 256:02x}:{len(ap_ids) % 256:02x}")
                freqs.append(fmhz)
        beacons += [(float(x), float(y), fi) for x, y in spaced(pts, 8.0)]
    if not nodes:
        raise ValueError("the floor plan has no free walkable space for walkers")
    P = np.array(nodes, float)
    names = [f.name for f in plan.floors]
    for tr in plan.transitions:
        try:
            fa, fb = names.index(tr.floor_from), names.index(tr.floor_to)
        except ValueError:
            continue
        if fa not in floor_nodes or fb not in floor_nodes:
            continue
        na = int(floor_nodes[fa][np.argmin(np.linalg.norm(P[floor_nodes[fa], :2] - tr.pos_from, axis=1))])
        nb = int(floor_nodes[fb][np.argmin(np.linalg.norm(P[floor_nodes[fb], :2] - tr.pos_to, axis=1))])
        kind = "lift" if tr.kind is TransitionKind.LIFT else "stairs"
        kinds[na] = kinds[nb] = kind
        edges.append((na, nb))
    # entrance on the ground floor: the outline point nearest to a free-space node, 12 m out of doors
    g = min(floor_nodes) if 0 not in floor_nodes else 0
    outline = plan.floors[g].outline
    comp = graph_components(len(nodes), edges)
    main = np.bincount(comp[floor_nodes[g]]).argmax()  # the entrance opens onto the ground floor's main concourse
    floor_nodes[g] = floor_nodes[g][comp[floor_nodes[g]] == main]
    gp = P[floor_nodes[g], :2]
    d = shapely.distance(outline.boundary, shapely.points(gp))
    j = int(np.argmin(d))
    near = shapely.ops.nearest_points(outline.boundary, shapely.Point(gp[j]))[0]
    ent = np.array([near.x, near.y])
    out_dir = ent - gp[j]
    out_dir = out_dir / max(np.linalg.norm(out_dir), 1e-9)
    ci = int(floor_nodes[g][j])
    en = add(ent[0], ent[1], g, "entrance")
    on = add(ent[0] + 12.0 * out_dir[0], ent[1] + 12.0 * out_dir[1], g, "outdoor")
    edges += [(ci, en), (en, on)]
    rfid.insert(0, (float(ent[0]), float(ent[1]), g))
    bx0, by0, bx1, by1 = unary_union([f.outline for f in plan.floors]).bounds
    beacon_ids = [f"simp{seed}_{i // 1000}_{i % 1000}" for i in range(len(beacons))]
    plan2 = FloorPlan(plan.site, plan.floors, plan.transitions, origin)
    return World(
        seed,
        plan2,
        float(bx1),
        float(by1),
        (float(by0), float(by1)),
        rooms,
        np.array(nodes, float),
        kinds,
        edges,
        np.array(aps, float).reshape(-1, 3),
        ap_ids,
        np.array(freqs),
        np.array(beacons, float).reshape(-1, 3),
        beacon_ids,
        np.array(rfid, float).reshape(-1, 3),
        (float(ent[0]), float(ent[1])),
        on,
        origin,
        x_min=float(bx0),
        y_min=float(by0),
        source=source,
    )
