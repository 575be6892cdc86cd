// World <-> screen and the drawing shared by the editor, the draw canvas and the thumbnails.
// The world is the mechanism's plane with y up, as in the dataset; the screen is CSS pixels
// with y down. Canvases are backed at the device's pixel ratio so lines stay sharp.

import { ACTUATED, FIXED, isCrank, links } from "./mechanism.js";

export class View {
  constructor() {
    this.scale = 400; // pixels per world unit
    this.cx = 0.5; // world point at the canvas centre
    this.cy = 0.5;
    this.width = 1;
    this.height = 1;
  }

  toScreen(p) {
    return [this.width / 2 + (p[0] - this.cx) * this.scale, this.height / 2 - (p[1] - this.cy) * this.scale];
  }

  toWorld(sx, sy) {
    return [this.cx + (sx - this.width / 2) / this.scale, this.cy - (sy - this.height / 2) / this.scale];
  }

  /** Show the box `b` ({minX, minY, maxX, maxY}) whole, at least `minExtent` wide and tall. */
  fit(b, minExtent = 0.2, margin = 0.08) {
    const w = Math.max(b.maxX - b.minX, minExtent);
    const h = Math.max(b.maxY - b.minY, minExtent);
    this.scale = Math.min(this.width / (w * (1 + 2 * margin)), this.height / (h * (1 + 2 * margin)));
    this.cx = (b.minX + b.maxX) / 2;
    this.cy = (b.minY + b.maxY) / 2;
  }

  /** Zoom by `factor` keeping the world point under (sx, sy) where it is. */
  zoomAt(sx, sy, factor) {
    const before = this.toWorld(sx, sy);
    this.scale = Math.min(Math.max(this.scale * factor, 5), 1e6);
    const after = this.toWorld(sx, sy);
    this.cx += before[0] - after[0];
    this.cy += before[1] - after[1];
  }

  panBy(dx, dy) {
    this.cx -= dx / this.scale;
    this.cy += dy / this.scale;
  }
}

/** The bounding box of point lists ([[x, y], ...] each); null when there are no points. */
export function bounds(...lists) {
  let b = null;
  for (const list of lists) {
    for (const p of list || []) {
      if (!b) b = { minX: p[0], minY: p[1], maxX: p[0], maxY: p[1] };
      b.minX = Math.min(b.minX, p[0]);
      b.minY = Math.min(b.minY, p[1]);
      b.maxX = Math.max(b.maxX, p[0]);
      b.maxY = Math.max(b.maxY, p[1]);
    }
  }
  return b;
}

/**
 * Keep `canvas` backed at its CSS size times the pixel ratio; calls `onResize(width, height)`
 * in CSS pixels once it is laid out and whenever its box changes. Returns the 2-D context.
 */
export function trackSize(canvas, onResize) {
  const ctx = canvas.getContext("2d");
  const apply = () => {
    const rect = canvas.getBoundingClientRect();
    const ratio = window.devicePixelRatio || 1;
    canvas.width = Math.max(1, Math.round(rect.width * ratio));
    canvas.height = Math.max(1, Math.round(rect.height * ratio));
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    onResize(rect.width, rect.height);
  };
  // The observer also reports the first size, after the caller has its context.
  new ResizeObserver(apply).observe(canvas);
  return ctx;
}

/** A distinct, readable colour per joint index. */
export function jointColor(j, alpha = 1) {
  const hue = (j * 137.508 + 200) % 360; // golden-angle steps keep neighbours apart
  return `hsla(${hue.toFixed(1)}, 70%, 42%, ${alpha})`;
}

export const COLORS = {
  grid: "#e8ecf2",
  unit: "#c3cad4",
  link: "#3b4452",
  crank: "#d9480f",
  joint: "#ffffff",
  ground: "#3b4452",
  pick: "#f59f00",
  select: "#2563eb",
  lock: "#c92a2a",
  curve: "rgba(31, 41, 51, 0.22)",
};

/** Light grid lines at a round world spacing, and the unit square the dataset lives in. */
export function drawGrid(ctx, view) {
  const step = 10 ** Math.floor(Math.log10(120 / view.scale)); // about 12-120 px apart
  const [x0, y1] = view.toWorld(0, 0);
  const [x1, y0] = view.toWorld(view.width, view.height);
  ctx.save();
  ctx.lineWidth = 1;
  ctx.strokeStyle = COLORS.grid;
  ctx.beginPath();
  for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) {
    const sx = Math.round(view.toScreen([x, 0])[0]) + 0.5;
    ctx.moveTo(sx, 0);
    ctx.lineTo(sx, view.height);
  }
  for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) {
    const sy = Math.round(view.toScreen([0, y])[1]) + 0.5;
    ctx.moveTo(0, sy);
    ctx.lineTo(view.width, sy);
  }
  ctx.stroke();
  const [ux, uy] = view.toScreen([0, 1]);
  ctx.strokeStyle = COLORS.unit;
  ctx.setLineDash([4, 4]);
  ctx.strokeRect(ux, uy, view.scale, view.scale);
  ctx.restore();
}

/** Stroke `points` (world); returns the screen points drawn, or null when too few to draw. */
export function drawPolyline(ctx, view, points, stroke, width = 1.5, closed = false) {
  if (!points || points.length < 2) return null;
  const screen = points.map((p) => view.toScreen(p));
  ctx.save();
  ctx.strokeStyle = stroke;
  ctx.lineWidth = width;
  ctx.lineJoin = "round";
  ctx.lineCap = "round";
  ctx.beginPath();
  screen.forEach(([sx, sy], i) => {
    if (i === 0) ctx.moveTo(sx, sy);
    else ctx.lineTo(sx, sy);
  });
  if (closed) ctx.closePath();
  ctx.stroke();
  ctx.restore();
  return screen;
}

/**
 * Each moving joint's path; a full turn is drawn closed, a path cut short by a lock is not.
 * Returns the screen points drawn per joint (null for a fixed joint), or null with no paths.
 */
export function drawPaths(ctx, view, mech, trajectories, { full = true, emphasize = -1 } = {}) {
  if (!trajectories) return null;
  return trajectories.map((path, j) => {
    if (mech.node_types[j] === FIXED) return null;
    const strong = j === emphasize;
    return drawPolyline(ctx, view, path, jointColor(j, strong ? 1 : 0.8), strong ? 3 : 1.5, full);
  });
}

/**
 * Links and joints at `pose` (one [x, y] per joint). Options: `picked` and `selected` joint
 * index sets drawn with rings, `labels` to number the joints, `fade` for a ghosted pose.
 */
export function drawMechanism(ctx, view, mech, pose, options = {}) {
  const { picked = [], selected = -1, labels = true, fade = false, radius = 6 } = options;
  ctx.save();
  if (fade) ctx.globalAlpha = 0.35;
  ctx.lineCap = "round";
  for (const [i, j] of links(mech)) {
    const [ax, ay] = view.toScreen(pose[i]);
    const [bx, by] = view.toScreen(pose[j]);
    ctx.strokeStyle = isCrank(i, j) ? COLORS.crank : COLORS.link;
    ctx.lineWidth = isCrank(i, j) ? 4 : 3;
    ctx.beginPath();
    ctx.moveTo(ax, ay);
    ctx.lineTo(bx, by);
    ctx.stroke();
  }
  pose.forEach((p, j) => {
    const [sx, sy] = view.toScreen(p);
    const kind = mech.node_types[j];
    if (kind === FIXED) {
      // A ground joint: a filled triangle under a ring, the usual pivot symbol.
      ctx.fillStyle = COLORS.ground;
      ctx.beginPath();
      ctx.moveTo(sx, sy);
      ctx.lineTo(sx - radius * 1.4, sy + radius * 2.2);
      ctx.lineTo(sx + radius * 1.4, sy + radius * 2.2);
      ctx.closePath();
      ctx.fill();
    }
    ctx.beginPath();
    ctx.arc(sx, sy, radius, 0, 2 * Math.PI);
    ctx.fillStyle = kind === ACTUATED ? COLORS.crank : COLORS.joint;
    ctx.fill();
    ctx.lineWidth = 2;
    ctx.strokeStyle = kind === FIXED ? COLORS.ground : jointColor(j);
    if (kind === ACTUATED) ctx.strokeStyle = COLORS.crank;
    ctx.stroke();
    const ring = picked.includes(j) ? COLORS.pick : j === selected ? COLORS.select : null;
    if (ring) {
      ctx.beginPath();
      ctx.arc(sx, sy, radius + 5, 0, 2 * Math.PI);
      ctx.lineWidth = 3;
      ctx.strokeStyle = ring;
      ctx.stroke();
    }
    if (labels) {
      ctx.fillStyle = COLORS.link;
      ctx.font = "11px system-ui, sans-serif";
      ctx.fillText(String(j), sx + radius + 3, sy - radius - 2);
    }
  });
  ctx.restore();
}

/** A red cross: where a joint could no longer be assembled. */
export function drawCross(ctx, view, p, size = 9) {
  const [sx, sy] = view.toScreen(p);
  ctx.save();
  ctx.strokeStyle = COLORS.lock;
  ctx.lineWidth = 3;
  ctx.beginPath();
  ctx.moveTo(sx - size, sy - size);
  ctx.lineTo(sx + size, sy + size);
  ctx.moveTo(sx + size, sy - size);
  ctx.lineTo(sx - size, sy + size);
  ctx.stroke();
  ctx.restore();
}
