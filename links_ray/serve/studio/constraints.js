// Design constraints drawn on the draw canvas: a pivot box (every fixed joint inside it) and a
// footprint box (every joint inside it over the whole turn), in the drawing's own frame (the
// frame its points are sent in), and the link-length limits typed beside them. A box is drawn
// by dragging; dragging near one of its corners moves that corner; drawing again replaces it.

import { COLORS } from "./view.js";

const KINDS = ["pivots", "footprint"];
const LABELS = { pivots: "pivots", footprint: "footprint" };
const STROKES = { pivots: "#7c3aed", footprint: "#0f766e" };
const CORNER_REACH_PX = 10; // a press this near a corner takes the corner, not a new box

export class Constraints {
  /** `ui`: pivots, footprint and clear buttons, maxLinkRatio, minLink, maxLink number inputs;
   * `onChange()` repaints. */
  constructor({ ui, onChange }) {
    this.ui = ui;
    this.onChange = onChange;
    this.boxes = { pivots: null, footprint: null }; // [xmin, ymin, xmax, ymax] or null
    this.mode = null; // the kind of box a drag draws, while its button is pressed
    this.anchor = null; // the fixed corner of the box being dragged
    ui.pivots.addEventListener("click", () => this.setMode("pivots"));
    ui.footprint.addEventListener("click", () => this.setMode("footprint"));
    ui.clear.addEventListener("click", () => this.clear());
    this.showMode();
  }

  /** Draw boxes of `kind` (again: back to drawing curves). */
  setMode(kind) {
    this.mode = this.mode === kind ? null : kind;
    this.showMode();
  }

  showMode() {
    this.ui.pivots.setAttribute("aria-pressed", String(this.mode === "pivots"));
    this.ui.footprint.setAttribute("aria-pressed", String(this.mode === "footprint"));
    this.ui.clear.disabled = !KINDS.some((kind) => this.boxes[kind]);
  }

  clear() {
    this.boxes = { pivots: null, footprint: null };
    this.mode = null;
    this.showMode();
    this.onChange();
  }

  // -- drawing a box: world points, and the view that shows them -----------------------------

  /** A press at `world`: starts a box (or takes a corner of the one there) if a box tool is
   * on; returns whether it did. */
  press(world, view) {
    if (!this.mode) return false;
    const box = this.boxes[this.mode];
    this.anchor = world;
    if (box) {
      const corners = [
        [box[0], box[1]],
        [box[2], box[1]],
        [box[2], box[3]],
        [box[0], box[3]],
      ];
      const [sx, sy] = view.toScreen(world);
      const near = corners.findIndex((c) => {
        const [cx, cy] = view.toScreen(c);
        return Math.hypot(cx - sx, cy - sy) <= CORNER_REACH_PX;
      });
      if (near >= 0) this.anchor = corners[(near + 2) % 4]; // the opposite corner stays
    }
    this.drag(world);
    return true;
  }

  drag(world) {
    if (!this.anchor) return;
    const [ax, ay] = this.anchor;
    const [x, y] = world;
    this.boxes[this.mode] = [Math.min(ax, x), Math.min(ay, y), Math.max(ax, x), Math.max(ay, y)];
    this.onChange();
  }

  release() {
    if (!this.anchor) return;
    this.anchor = null;
    const box = this.boxes[this.mode];
    if (box && (box[2] <= box[0] || box[3] <= box[1])) this.boxes[this.mode] = null; // a click
    this.showMode();
    this.onChange();
  }

  get dragging() {
    return this.anchor !== null;
  }

  // -- what is sent and shown -----------------------------------------------------------------

  /** The request's `constraints`, or null when none is set. */
  body() {
    const found = {};
    for (const kind of KINDS) if (this.boxes[kind]) found[kind] = this.boxes[kind].slice();
    const numbers = {
      max_link_ratio: this.ui.maxLinkRatio,
      min_link: this.ui.minLink,
      max_link: this.ui.maxLink,
    };
    for (const [name, input] of Object.entries(numbers)) {
      if (Number.isFinite(input.valueAsNumber)) found[name] = input.valueAsNumber;
    }
    return Object.keys(found).length ? found : null;
  }

  /** The boxes' corners, to keep them in view. */
  corners() {
    return KINDS.filter((kind) => this.boxes[kind]).map((kind) => {
      const b = this.boxes[kind];
      return [
        [b[0], b[1]],
        [b[2], b[3]],
      ];
    });
  }

  paint(ctx, view) {
    for (const kind of KINDS) {
      const box = this.boxes[kind];
      if (!box) continue;
      const [x0, y0] = view.toScreen([box[0], box[3]]);
      const [x1, y1] = view.toScreen([box[2], box[1]]);
      ctx.save();
      ctx.strokeStyle = STROKES[kind];
      ctx.fillStyle = STROKES[kind];
      ctx.lineWidth = 2;
      ctx.setLineDash(kind === "pivots" ? [6, 4] : [2, 3]);
      ctx.strokeRect(x0, y0, x1 - x0, y1 - y0);
      ctx.globalAlpha = 0.06;
      ctx.fillRect(x0, y0, x1 - x0, y1 - y0);
      ctx.globalAlpha = 1;
      ctx.font = "12px system-ui, sans-serif";
      ctx.fillText(LABELS[kind], x0 + 4, y0 + 14);
      ctx.restore();
    }
    if (this.mode && !this.dragging) {
      ctx.save();
      ctx.fillStyle = COLORS.link;
      ctx.font = "12px system-ui, sans-serif";
      ctx.fillText(`drag to draw the ${LABELS[this.mode]} box`, 8, view.height - 8);
      ctx.restore();
    }
  }
}
