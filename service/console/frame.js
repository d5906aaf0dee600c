// A camera's whole frame as the console draws it: the points POST /points reads from the file
// with each one's pixel (POST /detect's indices are pixels of an organized frame), which
// detection claims each, and the points drawn: at most MAX_DRAWN of them, shaded by how
// their surface faces the camera, tinted with the verdict colour of the detection claiming
// them.

import { rgb } from "./view.js";

const FRAME = 0x8c95a3; // a frame's points that no detection claims
export const VERDICT_COLOURS = { match: 0x2fb366, uncertain: 0xe0a526, no_match: 0xa3a9b1 };
const TINT = 0.6; // how far a claimed point's colour goes from FRAME to its detection's
const REACH = 4; // drawn pixels: how far apart the points a surface's shading comes from are
const MAX_DRAWN = 320_000; // a frame's points drawn at most: a whole VGA frame; 2048 x 1536 smooth

// POST /points?pixels=true's answer: the frame's points as the service reads them and, for
// an organized frame, each one's pixel, with the pixel -> point lookup (-1: no point).
export async function readFrame(response) {
  const buffer = await response.arrayBuffer();
  const count = Number(response.headers.get("X-Points"));
  const shape = response.headers.get("X-Shape")?.split(",").map(Number) ?? null;
  if (buffer.byteLength !== (shape ? 16 : 12) * count) {
    throw new Error(`/points answered ${buffer.byteLength} bytes for ${count} points`);
  }
  const implied = response.headers.get("X-Viewpoint");
  const pixels = shape ? new Uint32Array(buffer, 12 * count, count) : null;
  let lookup = null;
  if (shape) {
    lookup = new Int32Array(shape[0] * shape[1]).fill(-1);
    for (let i = 0; i < count; i++) lookup[pixels[i]] = i;
  }
  return {
    points: new Float32Array(buffer, 0, 3 * count),
    pixels,
    shape,
    lookup,
    viewpoint: implied ? implied.split(",").map(Number) : null,
  };
}

// index (as /detect answers it: a pixel of an organized frame, else a point) -> point, or -1.
function pointOfIndex({ points, lookup }) {
  const count = points.length / 3;
  if (!lookup) return (index) => (index < count ? index : -1);
  return (index) => (index < lookup.length ? lookup[index] : -1);
}

// How lit each point i of kept is, 0.3-1: an organized frame's points by how squarely their
// surface faces the camera (from the pixels reach away: the nearest differ mostly by depth
// noise), other clouds' by their range.
function shading(frame, kept, viewpoint, reach) {
  const { points, pixels, shape, lookup } = frame;
  const light = new Float32Array(kept.length).fill(1);
  const at = (i, c) => points[3 * i + c];
  const ranges = kept.map((i) => Math.hypot(...[0, 1, 2].map((c) => at(i, c) - viewpoint[c])));
  if (!lookup) {
    const sorted = ranges.filter((_, j) => j % 97 === 0).sort((x, y) => x - y);
    const [near, far] = [sorted[Math.floor(sorted.length * 0.02)], sorted[Math.floor(sorted.length * 0.98)]];
    ranges.forEach((range, j) => (light[j] = 1 - 0.6 * Math.min(1, Math.max(0, (range - near) / (far - near || 1)))));
    return light;
  }
  const width = shape[1];
  const neighbour = (p, step, inRow) => {
    const ahead = inRow ? (p % width) + step < width : p + step * width < lookup.length;
    const behind = inRow ? (p % width) - step >= 0 : p - step * width >= 0;
    const offset = inRow ? step : step * width;
    if (ahead && lookup[p + offset] >= 0) return [lookup[p + offset], 1];
    if (behind && lookup[p - offset] >= 0) return [lookup[p - offset], -1];
    return null;
  };
  kept.forEach((i, j) => {
    const [right, down] = [neighbour(pixels[i], reach, true), neighbour(pixels[i], reach, false)];
    if (!right || !down) return;
    const a = [0, 1, 2].map((c) => right[1] * (at(right[0], c) - at(i, c)));
    const b = [0, 1, 2].map((c) => down[1] * (at(down[0], c) - at(i, c)));
    const n = [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    const v = [0, 1, 2].map((c) => viewpoint[c] - at(i, c));
    const facing = Math.abs(n[0] * v[0] + n[1] * v[1] + n[2] * v[2]) / (Math.hypot(...n) * ranges[j] || 1);
    light[j] = 0.3 + 0.7 * facing;
  });
  return light;
}

// Which detection claims each point (-1: none), and the centre of each one's points.
export function claims(frame, detections) {
  const { points } = frame;
  const owner = new Int16Array(points.length / 3).fill(-1);
  const pointOf = pointOfIndex(frame);
  let unplaced = 0;
  const centres = detections.map((detection, k) => {
    const sum = [0, 0, 0];
    let placed = 0;
    for (const index of detection.indices) {
      const i = pointOf(index);
      if (i < 0) {
        unplaced++;
        continue;
      }
      owner[i] = k;
      placed++;
      for (let c = 0; c < 3; c++) sum[c] += points[3 * i + c];
    }
    return placed ? sum.map((value) => value / placed) : null;
  });
  return { owner, centres, unplaced };
}

// At most MAX_DRAWN of the frame's points, the claimed ones all kept up to half of them:
// of an organized frame the first point of each s x s block of pixels (every s-th pixel of
// every s-th row, where it has one), else evenly in the file's order.
// paint(k) colours them, shaded: FRAME, or tinted with their detection's verdict colour
// (faintly but for detection k's, unless k is null).
export function frameCloud(frame, owner, detections, viewpoint) {
  const { points, pixels, shape } = frame;
  const count = points.length / 3;
  let claimed = 0;
  for (let i = 0; i < count; i++) if (owner[i] >= 0) claimed++;
  const budgets = [MAX_DRAWN - Math.min(claimed, MAX_DRAWN / 2), MAX_DRAWN / 2]; // rest, claimed
  const sizes = [count - claimed, claimed];
  // each group's every stride-th point: of an organized frame, the first of each stride x
  // stride block of pixels (evenly spaced, as the shading needs); its first pixel where it has
  // one, and one of the others where pixels are missing in a pattern, as a depth image
  // registered to a larger colour image's (docs/decisions.md#pixels-missing-in-a-pattern)
  const select = (strides) => {
    const kept = [];
    const seen = [0, 0];
    const blocks = [new Set(), new Set()];
    for (let i = 0; i < count; i++) {
      const group = owner[i] >= 0 ? 1 : 0;
      const stride = strides[group];
      if (!pixels) {
        if (seen[group]++ % stride === 0) kept.push(i);
        continue;
      }
      const row = Math.floor(pixels[i] / shape[1]);
      const block = Math.floor(row / stride) * shape[1] + Math.floor((pixels[i] % shape[1]) / stride);
      if (!blocks[group].has(block)) {
        blocks[group].add(block); // the pixels come in order: the block's first is met first
        kept.push(i);
      }
    }
    return kept;
  };
  const ratios = sizes.map((size, g) => Math.max(1, size / budgets[g]));
  let strides = ratios.map((ratio) => Math.ceil(pixels ? Math.sqrt(ratio) : ratio));
  let kept = select(strides);
  while (kept.length > MAX_DRAWN) {
    strides = strides.map((stride) => stride + 1); // a grid's partial rows can overshoot
    kept = select(strides);
  }
  const drawn = new Float32Array(3 * kept.length);
  const owners = new Int16Array(kept.length);
  kept.forEach((i, j) => {
    owners[j] = owner[i];
    for (let c = 0; c < 3; c++) drawn[3 * j + c] = points[3 * i + c];
  });
  const base = rgb(FRAME);
  const tint = (k, share) => rgb(VERDICT_COLOURS[detections[k].verdict]).map((v, c) => base[c] + share * (v - base[c]));
  const light = shading(frame, kept, viewpoint, REACH * strides[0]);
  const colors = new Float32Array(3 * kept.length);
  const paint = (selected = null) => {
    const tints = detections.map((_, k) => tint(k, selected === null || k === selected ? TINT : TINT / 3));
    owners.forEach((k, j) => {
      const colour = k >= 0 ? tints[k] : base;
      for (let c = 0; c < 3; c++) colors[3 * j + c] = colour[c] * light[j];
    });
    return colors;
  };
  paint();
  const pointSize = pixels ? spacing(points) * strides[0] : undefined;
  const cloud = { points: drawn, colors, size: 0.35, pointSize, name: "frame" };
  return { cloud, paint, drawn: kept.length, tinted: owners.filter((k) => k >= 0).length };
}

// The largest distance of a cloud's points from their centroid.
export function radiusOf(points) {
  const count = points.length / 3;
  const centre = [0, 1, 2].map((c) => points.reduce((sum, v, i) => (i % 3 === c ? sum + v : sum), 0) / count);
  let radius = 0;
  for (let i = 0; i < points.length; i += 3) {
    radius = Math.max(radius, Math.hypot(points[i] - centre[0], points[i + 1] - centre[1], points[i + 2] - centre[2]));
  }
  return radius;
}

// An organized frame's points' spacing: the median distance between points next in the file
// (mostly neighbours in a row), so that the drawn points just about cover the surfaces.
function spacing(points) {
  const count = points.length / 3;
  const step = Math.max(1, Math.floor(count / 2000));
  const gaps = [];
  for (let i = 0; i + 1 < count; i += step) {
    const [a, b] = [3 * i, 3 * i + 3];
    gaps.push(Math.hypot(points[a] - points[b], points[a + 1] - points[b + 1], points[a + 2] - points[b + 2]));
  }
  gaps.sort((x, y) => x - y);
  return 1.2 * (gaps[gaps.length >> 1] ?? 0) || undefined;
}
