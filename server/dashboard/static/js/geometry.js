// Pure geometry of the page (no DOM, no Leaflet): tested with `node --test` (tests/js/).

// chi-square quantile, 2 degrees of freedom, p = 0.95: -2 ln(1 - 0.95) = 5.991
export const CHI2_95_2DOF = -2 * Math.log(0.05);

// The 95 % ellipse of a 2x2 position covariance given by its upper triangle [xx, xy, yy] (m^2):
// eigenvalues l1 >= l2 of [[xx, xy], [xy, yy]] are (xx + yy)/2 +- sqrt(((xx - yy)/2)^2 + xy^2); the
// semi-axes are sqrt(5.991 l_i) along the eigenvectors, the major one at angle
// theta = atan2(2 xy, xx - yy) / 2 from the x axis (radians, counter-clockwise).
// Returns null for a covariance that is not one (negative or non-finite variances).
export function ellipse95(cov) {
  if (!cov || cov.length !== 3) return null;
  const [xx, xy, yy] = cov.map(Number);
  if (![xx, xy, yy].every(Number.isFinite) || xx < 0 || yy < 0) return null;
  const mean = (xx + yy) / 2;
  const root = Math.hypot((xx - yy) / 2, xy);
  const l1 = mean + root;
  const l2 = Math.max(mean - root, 0); // rounding can push a singular covariance's l2 below 0
  return { a: Math.sqrt(CHI2_95_2DOF * l1), b: Math.sqrt(CHI2_95_2DOF * l2), angle: 0.5 * Math.atan2(2 * xy, xx - yy) };
}

// n points [x, y] (site frame, m) on the 95 % ellipse around (x, y); [] without an ellipse.
export function ellipsePoints(x, y, cov, n = 48) {
  const e = ellipse95(cov);
  if (!e) return [];
  const c = Math.cos(e.angle);
  const s = Math.sin(e.angle);
  const out = [];
  for (let k = 0; k < n; k++) {
    const u = (2 * Math.PI * k) / n;
    const ex = e.a * Math.cos(u);
    const ey = e.b * Math.sin(u);
    out.push([x + c * ex - s * ey, y + s * ex + c * ey]);
  }
  return out;
}

// Colour of a heat-layer value: a perceptual ramp (dark blue -> teal -> yellow, as viridis) over
// [vmin, vmax], log10 when scale is "log" (support counts span decades). Returns [r, g, b] 0-255.
const RAMP = [
  [68, 1, 84],
  [59, 82, 139],
  [33, 145, 140],
  [94, 201, 98],
  [253, 231, 37],
];

export function rampColour(v, vmin, vmax, scale = "linear") {
  let lo = vmin;
  let hi = vmax;
  let x = v;
  if (scale === "log") {
    lo = Math.log10(Math.max(vmin, 1e-3));
    hi = Math.log10(Math.max(vmax, 1e-3));
    x = Math.log10(Math.max(v, 1e-3));
  }
  let f = hi > lo ? (x - lo) / (hi - lo) : 1;
  f = Math.min(1, Math.max(0, f));
  const pos = f * (RAMP.length - 1);
  const i = Math.min(RAMP.length - 2, Math.floor(pos));
  const w = pos - i;
  return RAMP[i].map((c, k) => Math.round(c + w * (RAMP[i + 1][k] - c)));
}

// A stable colour per device id (hue from a string hash), as an HSL CSS colour.
export function deviceColour(id) {
  let h = 2166136261;
  for (let i = 0; i < id.length; i++) {
    h ^= id.charCodeAt(i);
    h = Math.imul(h, 16777619);
  }
  return `hsl(${(h >>> 0) % 360}, 70%, 42%)`;
}
