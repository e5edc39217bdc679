// The page's model of the live state, and the rules the view follows (no DOM, no Leaflet): tested
// with `node --test` (tests/js/).
//
// The server sends a "snapshot" on connect, then "delta" frames (at most 10 per second): each delta
// carries only what changed. applyFrame folds a frame into the model and returns the keys of the
// devices it changed, so the view redraws only those, in place. Several frames applied before a
// redraw coalesce: a device's newest fields win, its new track points are appended once each.

// Raw track points the page keeps per device (the server keeps 300).
export const TRACK_POINTS = 300;

export function newModel() {
  return {
    devices: new Map(), // "site/device" -> device
    sites: new Map(), // site id -> {map_version, map_source, progress, slam}
    offset: 0, // server clock - local clock, s (the newest frame's "now")
    staleS: 10,
    lostS: 60,
  };
}

export function deviceKey(site, id) {
  return `${site}/${id}`;
}

// Fold `frame` into `model`; `localNow` is the local clock at arrival (s). Returns the set of device
// keys changed (a snapshot: every key, the model first emptied of devices and sites).
export function applyFrame(model, frame, localNow) {
  const changed = new Set();
  if (typeof frame.now === "number") model.offset = frame.now - localNow;
  if (frame.type === "snapshot") {
    for (const k of model.devices.keys()) changed.add(k); // devices gone since: removed by the view
    model.devices.clear();
    model.sites.clear();
    if (frame.stale_s) model.staleS = frame.stale_s;
    if (frame.lost_s) model.lostS = frame.lost_s;
  }
  for (const s of frame.sites || []) {
    model.sites.set(s.id, { ...(model.sites.get(s.id) || {}), ...s });
  }
  for (const e of frame.devices || []) {
    const key = deviceKey(e.site, e.id);
    const d = model.devices.get(key) || { id: e.id, site: e.site, pts: [], corr: null, region: null, rej: {}, online: false };
    for (const f of ["floor", "seen", "t", "x", "y", "cov", "online", "rej"]) {
      if (f in e) d[f] = e[f];
    }
    if ("corr" in e) d.corr = e.corr;
    if ("region" in e) d.region = e.region;
    if (e.pts) {
      d.pts = e.reset ? e.pts.slice() : d.pts.concat(e.pts);
      if (d.pts.length > TRACK_POINTS) d.pts = d.pts.slice(d.pts.length - TRACK_POINTS);
    }
    model.devices.set(key, d);
    changed.add(key);
  }
  return changed;
}

// "live", "stale" or "lost" for a device last heard `ageS` seconds ago.
export function staleness(ageS, staleS, lostS) {
  if (!(ageS < lostS)) return "lost"; // NaN (never heard) is lost too
  return ageS < staleS ? "live" : "stale";
}

// Seconds since the device was last heard, on the server's clock.
export function ageOf(model, d, localNow) {
  return localNow + model.offset - (d.seen || 0);
}

// Head count per floor of a site: devices with a position that are not lost. Map floor -> count.
export function floorCounts(model, site, localNow) {
  const counts = new Map();
  for (const d of model.devices.values()) {
    if (d.site !== site || d.x === undefined || d.x === null) continue;
    if (staleness(ageOf(model, d, localNow), model.staleS, model.lostS) === "lost") continue;
    const f = d.floor ?? "?";
    counts.set(f, (counts.get(f) || 0) + 1);
  }
  return counts;
}

// The floors to offer for a site: the plan's (in level order) then any a device reports.
export function floorsOf(planFloors, model, site) {
  const out = planFloors.slice();
  for (const d of model.devices.values()) {
    if (d.site === site && d.x !== undefined && d.x !== null) {
      const f = d.floor ?? "?";
      if (!out.includes(f)) out.push(f);
    }
  }
  return out;
}

// A device's raw track split into runs on `floor`: arrays of [x, y] (a walk leaving the floor and
// coming back is two runs, never a line through the other floor).
export function runsOnFloor(pts, floor, maxPoints = TRACK_POINTS) {
  const runs = [];
  let run = null;
  const start = Math.max(0, pts.length - maxPoints);
  for (let i = start; i < pts.length; i++) {
    const [x, y, f] = pts[i];
    if ((f ?? "?") === floor) {
      if (!run) {
        run = [];
        runs.push(run);
      }
      run.push([x, y]);
    } else {
      run = null;
    }
  }
  return runs;
}

// The corrected track's runs on `floor` (its "xy" and "floor" columns).
export function correctedRunsOnFloor(corr, floor) {
  if (!corr) return [];
  return runsOnFloor(
    corr.xy.map((p, i) => [p[0], p[1], corr.floor[i]]),
    floor,
    corr.xy.length,
  );
}

// An answer is still wanted when the page shows what was asked when it was sent: a coverage
// response for another site, floor or transmitter (the user switched meanwhile) is dropped, and so
// is any but the newest request's.
export function isCurrent(request, shown, newestSeq) {
  return request.seq === newestSeq && request.site === shown.site && request.floor === shown.floor && request.tx === shown.tx;
}
