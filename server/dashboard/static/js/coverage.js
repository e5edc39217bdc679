// The radio map's coverage grid as an image (browser only: a canvas, drawn once per response).
import { rampColour } from "./geometry.js";

// A data: URL of the grid (one pixel per cell, north up) and its legend's range.
export function gridImage(cov, alpha = 200) {
  const canvas = document.createElement("canvas");
  canvas.width = cov.nx;
  canvas.height = cov.ny;
  const ctx = canvas.getContext("2d");
  const img = ctx.createImageData(cov.nx, cov.ny);
  for (let iy = 0; iy < cov.ny; iy++) {
    for (let ix = 0; ix < cov.nx; ix++) {
      const v = cov.values[iy * cov.nx + ix];
      if (v === null || v === undefined) continue;
      const [r, g, b] = rampColour(v, cov.vmin, cov.vmax, cov.scale);
      const o = ((cov.ny - 1 - iy) * cov.nx + ix) * 4; // row 0 of the image is the north edge
      img.data[o] = r;
      img.data[o + 1] = g;
      img.data[o + 2] = b;
      img.data[o + 3] = alpha;
    }
  }
  ctx.putImageData(img, 0, 0);
  return canvas.toDataURL("image/png");
}

// The grid's bounds as Leaflet [[south, west], [north, east]] in L.CRS.Simple ([y, x], m).
export function gridBounds(cov) {
  return [
    [cov.y0, cov.x0],
    [cov.y0 + cov.ny * cov.cell, cov.x0 + cov.nx * cov.cell],
  ];
}

// A legend bar as a data: URL (width x 1 pixels over the ramp).
export function legendImage(scale, width = 160) {
  const canvas = document.createElement("canvas");
  canvas.width = width;
  canvas.height = 1;
  const ctx = canvas.getContext("2d");
  const img = ctx.createImageData(width, 1);
  for (let i = 0; i < width; i++) {
    const [r, g, b] = rampColour(i, 0, width - 1, "linear");
    img.data.set([r, g, b, 255], i * 4);
  }
  ctx.putImageData(img, 0, 0);
  return canvas.toDataURL("image/png");
}
