// Draw to retrieve: the user draws a curve, POST /api/retrieve finds curated paths of that
// shape (or POST /api/synthesize finds them and refines their mechanisms onto the curve), and
// a chosen result's mechanism (already in the drawing's frame, placed by the server) is
// simulated and animated over the curve.

import { explain, limits, postJson, postJsonLines } from "./api.js";
import { parseMechanism } from "./mechanism.js";
import {
  COLORS,
  View,
  bounds,
  drawGrid,
  drawMechanism,
  drawPaths,
  drawPolyline,
  trackSize,
} from "./view.js";

const STEPS = 200;
const STEPS_PER_SECOND = 50;
const MIN_SPACING_PX = 2; // finer than this only adds points, not shape
const MAX_DRAWN_POINTS = 5000; // a hand-drawn curve needs no more, unless the API takes fewer
const UNIT = { minX: 0, minY: 0, maxX: 1, maxY: 1 };

export class Retriever {
  /** `ui`: retrieve, synthesize, clear, open, k, status, list; `editor` receives "Open in
   * editor". */
  constructor({ canvas, ui, notify, editor }) {
    this.canvas = canvas;
    this.ui = ui;
    this.notify = notify;
    this.editor = editor;
    this.view = new View();
    this.points = []; // the drawn curve, world coordinates (the editor's frame)
    this.drawing = null; // pointer id while a stroke is under way
    this.results = [];
    this.chosen = null; // {index, result, trajectories}; index -1 while a synthesis runs
    this.live = []; // a running synthesis's best chamfers so far, as they fell
    this.runs = 0; // searches started, and drawings: only the latest search's answers count
    this.frame = 0;
    this.ctx = trackSize(canvas, (width, height) => {
      this.view.width = width;
      this.view.height = height;
      this.fitView();
      this.paint();
    });
    canvas.addEventListener("pointerdown", (e) => this.pointerDown(e));
    canvas.addEventListener("pointermove", (e) => this.pointerMove(e));
    canvas.addEventListener("pointerup", (e) => this.pointerUp(e));
    canvas.addEventListener("pointercancel", (e) => this.pointerUp(e));
    ui.retrieve.addEventListener("click", () => this.retrieve());
    ui.synthesize?.addEventListener("click", () => this.retrieve(true));
    ui.clear.addEventListener("click", () => this.clear());
    ui.open.addEventListener("click", () => this.openInEditor());
  }

  say(text, bad = false) {
    this.ui.status.textContent = text;
    this.ui.status.classList.toggle("bad", bad);
  }

  /** The unit square while drawing; the curve and the chosen mechanism once there is one. */
  fitView() {
    if (this.chosen) {
      this.view.fit(bounds(this.points, ...this.chosen.trajectories), 0.2, 0.06);
    } else {
      this.view.fit(UNIT, 1, 0.04);
    }
  }

  // -- drawing the curve --------------------------------------------------------------------

  local(e) {
    const rect = this.canvas.getBoundingClientRect();
    return [e.clientX - rect.left, e.clientY - rect.top];
  }

  pointerDown(e) {
    if (e.button !== undefined && e.button > 0) return;
    if (this.drawing !== null) return; // one finger draws; a second is ignored
    this.canvas.setPointerCapture(e.pointerId);
    this.drawing = e.pointerId;
    this.runs += 1;
    this.stop();
    this.results = [];
    this.renderResults();
    this.fitView(); // back to the drawing frame if a result had zoomed out
    const [sx, sy] = this.local(e);
    this.points = [this.view.toWorld(sx, sy)];
    this.lastScreen = [sx, sy];
    this.say("Drawing…");
    this.paint();
  }

  pointerMove(e) {
    if (e.pointerId !== this.drawing) return;
    // Coalesced events carry the points a fast stroke would otherwise skip.
    const events = e.getCoalescedEvents ? e.getCoalescedEvents() : [];
    for (const event of events.length ? events : [e]) {
      const [sx, sy] = this.local(event);
      const [lx, ly] = this.lastScreen;
      if (Math.hypot(sx - lx, sy - ly) < MIN_SPACING_PX) continue;
      if (this.points.length >= Math.min(MAX_DRAWN_POINTS, limits.max_points ?? Infinity)) break;
      this.points.push(this.view.toWorld(sx, sy));
      this.lastScreen = [sx, sy];
    }
    this.paint();
  }

  pointerUp(e) {
    if (e.pointerId !== this.drawing) return;
    this.drawing = null;
    this.say(`${this.points.length} points drawn: press “Find mechanisms”.`);
    this.paint();
  }

  clear() {
    this.runs += 1;
    this.stop();
    this.points = [];
    this.results = [];
    this.renderResults();
    this.fitView();
    this.say("");
    this.paint();
  }

  // -- retrieval ----------------------------------------------------------------------------

  /** Retrieve (or, with `synthesize`, retrieve and refine) mechanisms for the drawn curve. */
  async retrieve(synthesize = false) {
    if (!this.points.length) {
      this.say("Draw a curve first: press and drag on the drawing area.", true);
      return;
    }
    const k = this.ui.k.valueAsNumber;
    const floor = this.ui.minTransmission ? this.ui.minTransmission.valueAsNumber : 0;
    const body = {
      points: this.points,
      ...(Number.isFinite(k) ? { k } : {}),
      ...(Number.isFinite(floor) && floor > 0 ? { min_transmission: floor } : {}),
    };
    const what = synthesize ? "Synthesis" : "Retrieval";
    const buttons = [this.ui.retrieve, this.ui.synthesize].filter(Boolean);
    buttons.forEach((button) => (button.disabled = true));
    this.say(synthesize ? "Searching, then refining (a few seconds)…" : "Searching…");
    this.live = [];
    const run = ++this.runs; // a new drawing or search makes this one's progress stale
    try {
      const answer = synthesize
        ? await postJsonLines("/api/synthesize", { ...body, stream: true }, (line) => {
            if (run === this.runs) this.showProgress(line);
          })
        : await postJson("/api/retrieve", body);
      if (run !== this.runs) return;
      if (answer.data && answer.data.error && answer.status === 200) {
        this.say(`${what} failed: ${answer.data.error}`, true);
        return;
      }
      if (answer.status !== 200 || !answer.data || !Array.isArray(answer.data.results)) {
        this.say(`${what} failed: ${explain(answer)}`, true);
        return;
      }
      this.stop();
      this.results = answer.data.results;
      this.renderResults();
      const count = this.results.length;
      const took = `${synthesize ? "synthesis" : "search"} ${answer.data.took_ms.toFixed(0)} ms`;
      const trip = `round trip ${answer.ms.toFixed(0)} ms`;
      const found = `${count} mechanisms, best first (${took}, ${trip}).`;
      if (synthesize && count) {
        // A synthesis ends on its best mechanism, animating over the curve.
        await this.choose(0, `${found} `);
        return;
      }
      this.say(
        count
          ? `${found} Choose one to watch it trace your curve.`
          : body.min_transmission
            ? `No curated path keeps a transmission angle of ${floor}°: lower it.`
            : "No curated paths to compare with: the dataset is empty.",
      );
    } catch (err) {
      this.say(`${what} failed: ${err.message}`, true);
      this.notify(`${what} failed: ${err.message}`, "network");
    } finally {
      buttons.forEach((button) => (button.disabled = false));
    }
  }

  /** One line of a streamed synthesis: the best so far moves and traces over the curve. */
  showProgress(line) {
    const best = line.progress;
    if (!best) return;
    const first = !this.chosen;
    this.live.push(best.chamfer);
    this.canvas.dataset.progress = String(this.live.length);
    this.chosen = { index: -1, result: best, trajectories: best.trajectories };
    this.fitView(); // each better mechanism may reach elsewhere: keep it and the curve in view
    this.say(
      `Refining: chamfer ${best.chamfer.toPrecision(4)} ` +
        `(retrieved ${best.retrieved_chamfer.toPrecision(4)}), ` +
        `${(best.elapsed_ms / 1000).toFixed(1)} s…`,
    );
    this.start(!first);
  }

  renderResults() {
    const list = this.ui.list;
    list.replaceChildren();
    this.results.forEach((result, i) => {
      const item = document.createElement("li");
      item.dataset.testid = "result";
      item.dataset.chamfer = String(result.chamfer);
      const angle = result.min_transmission_deg;
      if (typeof angle === "number") item.dataset.transmission = String(angle);
      const button = document.createElement("button");
      button.type = "button";
      button.setAttribute("aria-pressed", "false");
      const thumb = document.createElement("canvas");
      thumb.setAttribute("aria-hidden", "true");
      const text = document.createElement("span");
      const chamfer = document.createElement("span");
      chamfer.className = "chamfer";
      chamfer.textContent = `#${i + 1}  chamfer ${result.chamfer.toPrecision(4)}`;
      const meta = document.createElement("span");
      meta.className = "meta";
      const n = result.mechanism.node_types.length;
      // A synthesis result has no stored joint: it says what refinement gained instead.
      meta.textContent =
        result.retrieved_chamfer === undefined
          ? ` · mechanism ${result.mechanism_id}, joint ${result.joint} ` +
            `(${n} joints after reduction)` +
            (typeof angle === "number" ? `, least transmission ${angle.toFixed(1)}°` : "")
          : ` · refined from ${result.retrieved_chamfer.toPrecision(4)}, ` +
            `from mechanism ${result.mechanism_id} (${n} joints)`;
      text.append(chamfer, meta);
      button.append(thumb, text);
      button.addEventListener("click", () => this.choose(i));
      item.append(button);
      list.append(item);
      drawThumbnail(thumb, result.points ?? result.path);
    });
    this.ui.open.disabled = true;
  }

  /** Simulate result `i`'s mechanism and animate it over the drawn curve; `lead` opens the
   * message that says so. */
  async choose(i, lead = "") {
    const result = this.results[i];
    this.ui.list.querySelectorAll("button").forEach((button, j) => {
      button.setAttribute("aria-pressed", String(i === j));
    });
    this.say(`Simulating result #${i + 1}…`);
    try {
      const answer = await postJson("/api/simulate", { ...result.mechanism, steps: STEPS });
      if (answer.status !== 200 || !answer.data || !answer.data.trajectories) {
        this.say(`Cannot animate result #${i + 1}: ${explain(answer)}`, true);
        return;
      }
      if (this.results[i] !== result) return; // a newer search replaced the list meanwhile
      this.chosen = { index: i, result, trajectories: answer.data.trajectories };
    } catch (err) {
      this.say(`Cannot animate result #${i + 1}: ${err.message}`, true);
      return;
    }
    this.ui.open.disabled = false;
    this.fitView();
    this.say(
      `${lead}Result #${i + 1}: joint ${result.mechanism_joint} (thick) traces your curve ` +
        `(grey) with chamfer ${result.chamfer.toPrecision(4)}.`,
    );
    this.start();
  }

  openInEditor() {
    if (!this.chosen) return;
    try {
      this.editor.load(parseMechanism(this.chosen.result.mechanism));
    } catch (err) {
      this.say(`Cannot open it: ${err.message}`, true);
      return;
    }
    this.editor.canvas.scrollIntoView({ behavior: "smooth", block: "center" });
    this.editor.canvas.focus({ preventScroll: true });
  }

  // -- animation ----------------------------------------------------------------------------

  /** Animate the chosen mechanism; `keepFrame`: from where the last one was (a synthesis's
   * better mechanism takes over mid-turn, so the motion does not jump back). */
  start(keepFrame = false) {
    const chosen = this.chosen;
    let last = performance.now();
    if (!keepFrame) this.frame = 0;
    this.canvas.dataset.animating = "true";
    const tick = (now) => {
      if (this.chosen !== chosen) return; // stopped, or another result was chosen
      // rAF's timestamp can precede `last`, taken when the loop started: never step back.
      this.frame = (this.frame + (Math.max(now - last, 0) / 1000) * STEPS_PER_SECOND) % STEPS;
      last = now;
      this.canvas.dataset.frame = String(Math.floor(this.frame));
      this.paint();
      requestAnimationFrame(tick);
    };
    requestAnimationFrame(tick);
  }

  stop() {
    this.chosen = null;
    this.canvas.dataset.animating = "false";
    this.ui.open.disabled = true;
  }

  paint() {
    const { ctx, view } = this;
    ctx.clearRect(0, 0, view.width, view.height);
    drawGrid(ctx, view);
    drawPolyline(ctx, view, this.points, COLORS.curve, 7);
    if (!this.chosen) return;
    const { result, trajectories } = this.chosen;
    const mech = result.mechanism;
    const t = Math.floor(this.frame);
    drawPaths(ctx, view, mech, trajectories, { emphasize: result.mechanism_joint });
    const pose = trajectories.map((path) => path[t]);
    drawMechanism(ctx, view, mech, pose, { selected: result.mechanism_joint, labels: false });
  }
}

/** A result's path (normalized, or a synthesis result's in the drawing's frame) in a small
 * canvas. */
function drawThumbnail(canvas, points) {
  const size = 56;
  const ratio = window.devicePixelRatio || 1;
  canvas.width = size * ratio;
  canvas.height = size * ratio;
  const ctx = canvas.getContext("2d");
  ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
  const view = new View();
  view.width = size;
  view.height = size;
  view.fit(bounds(points), 0.05, 0.1);
  drawPolyline(ctx, view, points, COLORS.select, 1.5);
}
