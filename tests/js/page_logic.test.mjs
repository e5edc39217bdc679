// The page's pure logic (server/dashboard/static/js/geometry.js, state.js) under `node --test`;
// tests/test_dashboard_http.py runs this file where Node is present.
import test from "node:test";
import assert from "node:assert/strict";
import { ellipse95, ellipsePoints, CHI2_95_2DOF, rampColour } from "../../server/dashboard/static/js/geometry.js";
import { newModel, applyFrame, staleness, floorCounts, runsOnFloor, isCurrent, TRACK_POINTS } from "../../server/dashboard/static/js/state.js";

const close = (a, b, tol = 1e-9) => assert.ok(Math.abs(a - b) <= tol, `${a} != ${b}`);

test("95 % ellipse of a diagonal covariance: semi-axes sqrt(5.991 sigma^2) along the axes", () => {
  close(CHI2_95_2DOF, 5.991464547107979);
  const e = ellipse95([4, 0, 1]);
  close(e.a, Math.sqrt(CHI2_95_2DOF * 4));
  close(e.b, Math.sqrt(CHI2_95_2DOF * 1));
  close(e.angle, 0);
});

test("95 % ellipse of a correlated covariance: eigenvalues and the major axis at 45 degrees", () => {
  // [[2, 1], [1, 2]]: eigenvalues 3 and 1, major axis along (1, 1)
  const e = ellipse95([2, 1, 2]);
  close(e.a, Math.sqrt(CHI2_95_2DOF * 3));
  close(e.b, Math.sqrt(CHI2_95_2DOF * 1));
  close(e.angle, Math.PI / 4);
  // every point p of the ellipse has Mahalanobis distance^2 p' C^-1 p = 5.991
  const inv = [2 / 3, -1 / 3, 2 / 3]; // inverse of [[2, 1], [1, 2]]
  for (const [x, y] of ellipsePoints(10, 20, [2, 1, 2], 48)) {
    const dx = x - 10;
    const dy = y - 20;
    close(inv[0] * dx * dx + 2 * inv[1] * dx * dy + inv[2] * dy * dy, CHI2_95_2DOF, 1e-9);
  }
  assert.equal(ellipsePoints(0, 0, [2, 1, 2], 48).length, 48);
});

test("no ellipse for what is not a covariance", () => {
  for (const bad of [null, [1, 0], [-1, 0, 1], [1, 0, NaN], [1, 0, -0.5]]) assert.equal(ellipse95(bad), null);
  assert.deepEqual(ellipsePoints(0, 0, null), []);
  // a singular one (rounded slightly below zero) keeps a zero minor axis
  assert.equal(ellipse95([1, 1, 1]).b, 0);
});

test("staleness: live below stale_s, stale below lost_s, lost after (and when never heard)", () => {
  assert.equal(staleness(0, 10, 60), "live");
  assert.equal(staleness(9.99, 10, 60), "live");
  assert.equal(staleness(10, 10, 60), "stale");
  assert.equal(staleness(59.9, 10, 60), "stale");
  assert.equal(staleness(60, 10, 60), "lost");
  assert.equal(staleness(NaN, 10, 60), "lost");
});

test("frames coalesce: the newest fields win, each track point is appended once, a reset replaces", () => {
  const m = newModel();
  applyFrame(m, { type: "snapshot", now: 1000, stale_s: 5, lost_s: 30, sites: [{ id: "s" }], devices: [{ id: "a", site: "s", floor: "F1", x: 1, y: 1, seen: 1000, pts: [[1, 1, "F1", 0]], reset: true }] }, 1000);
  assert.equal(m.staleS, 5);
  const changed = new Set();
  for (const k of applyFrame(m, { type: "delta", now: 1001, devices: [{ id: "a", site: "s", x: 2, y: 2, seen: 1001, pts: [[2, 2, "F1", 1]] }] }, 1001)) changed.add(k);
  for (const k of applyFrame(m, { type: "delta", now: 1002, devices: [{ id: "a", site: "s", x: 3, y: 3, floor: "F2", seen: 1002, pts: [[3, 3, "F2", 2]] }] }, 1002)) changed.add(k);
  const d = m.devices.get("s/a");
  assert.deepEqual([...changed], ["s/a"]);
  assert.deepEqual([d.x, d.y, d.floor], [3, 3, "F2"]);
  assert.deepEqual(d.pts.map((p) => p[3]), [0, 1, 2]);
  applyFrame(m, { type: "delta", now: 1003, devices: [{ id: "a", site: "s", pts: [[9, 9, "F2", 9]], reset: true }] }, 1003);
  assert.deepEqual(m.devices.get("s/a").pts.map((p) => p[3]), [9]);
  // the ring keeps the newest TRACK_POINTS
  const many = Array.from({ length: TRACK_POINTS + 50 }, (_, i) => [i, i, "F2", i]);
  applyFrame(m, { type: "delta", now: 1004, devices: [{ id: "a", site: "s", pts: many }] }, 1004);
  const pts = m.devices.get("s/a").pts;
  assert.equal(pts.length, TRACK_POINTS);
  assert.equal(pts.at(-1)[3], TRACK_POINTS + 49);
  // a snapshot starts over: a device it does not name is gone (and reported changed)
  const gone = applyFrame(m, { type: "snapshot", now: 1005, sites: [], devices: [] }, 1005);
  assert.ok(gone.has("s/a"));
  assert.equal(m.devices.size, 0);
});

test("head count per floor: devices with a position that are not lost, on the server's clock", () => {
  const m = newModel();
  // the local clock runs 100 s behind the server's: ages use the server's
  applyFrame(m, { type: "snapshot", now: 1100, stale_s: 10, lost_s: 60, sites: [], devices: [
    { id: "a", site: "s", floor: "F1", x: 0, y: 0, seen: 1099 },
    { id: "b", site: "s", floor: "F1", x: 0, y: 0, seen: 1070 }, // stale: counted
    { id: "c", site: "s", floor: "F2", x: 0, y: 0, seen: 1000 }, // lost: not counted
    { id: "d", site: "s", floor: null, x: 0, y: 0, seen: 1099 }, // no floor: "?"
    { id: "e", site: "other", floor: "F1", x: 0, y: 0, seen: 1099 },
    { id: "f", site: "s", floor: "F1", seen: 1099 }, // no position yet
  ] }, 1000);
  assert.deepEqual(Object.fromEntries(floorCounts(m, "s", 1000)), { F1: 2, "?": 1 });
});

test("a track is split into runs on the shown floor", () => {
  const pts = [[0, 0, "F1"], [1, 0, "F1"], [2, 0, "F2"], [3, 0, "F1"], [4, 0, null]];
  assert.deepEqual(runsOnFloor(pts, "F1"), [[[0, 0], [1, 0]], [[3, 0]]]);
  assert.deepEqual(runsOnFloor(pts, "?"), [[[4, 0]]]);
});

test("a coverage answer is drawn only for what is shown and only the newest request's", () => {
  const shown = { site: "s", floor: "F2", tx: null };
  assert.ok(isCurrent({ seq: 3, site: "s", floor: "F2", tx: null }, shown, 3));
  assert.ok(!isCurrent({ seq: 2, site: "s", floor: "F1", tx: null }, shown, 3)); // the floor changed meanwhile
  assert.ok(!isCurrent({ seq: 2, site: "s", floor: "F2", tx: null }, shown, 3)); // an older request for the same floor
  assert.ok(!isCurrent({ seq: 3, site: "s", floor: "F2", tx: "ap1" }, shown, 3));
});

test("heat ramp: ends of the range are the ramp's ends, log scale spreads decades evenly", () => {
  assert.deepEqual(rampColour(0, 0, 1), [68, 1, 84]);
  assert.deepEqual(rampColour(1, 0, 1), [253, 231, 37]);
  assert.deepEqual(rampColour(5, 0, 1), [253, 231, 37]); // clamped
  assert.deepEqual(rampColour(10, 1, 100, "log"), rampColour(0.5, 0, 1));
});
