// Draw to retrieve: the user draws a curve (or opens one from a drawing's file), POST
// /api/retrieve finds curated paths of that shape (or POST /api/synthesize finds them and
// refines their mechanisms onto the curve, within the joints, constraints and timing asked
// for), and a chosen result's mechanism (already in the drawing's frame, placed by the server)
// is simulated and animated over the curve.

import { explain, limits, postJson, postJsonLines } from "./api.js";
import { markFront, renderFront } from "./front.js";
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
  /** `ui`: retrieve, synthesize, clear, open, k, status, list, and the synthesis's options
   * maxJoints, front, timed, partial, with frontTable and unmet to show its answer;
   * `constraints` (a Constraints) draws its boxes here; `editor` receives "Open in editor". */
  constructor({ canvas, ui, notify, editor, constraints }) {
    this.canvas = canvas;
    this.ui = ui;
    this.notify = notify;
    this.editor = editor;
    this.constraints = constraints;
    this.view = new View();
    this.points = []; // the drawn curve, world coordinates (the editor's frame)
    this.frameBox = UNIT; // what the view shows while there is no result: a file's curve
    this.boxing = null; // pointer id while a constraint box is drawn
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

  /** The unit square (or an opened curve) while drawing; the curve and the chosen mechanism
   * once there is one; the constraint boxes always. */
  fitView() {
    const frame = this.frameBox;
    const size = Math.max(frame.maxX - frame.minX, frame.maxY - frame.minY);
    const boxes = this.constraints ? this.constraints.corners() : [];
    if (this.chosen) {
      this.view.fit(bounds(this.points, ...this.chosen.trajectories, ...boxes), 0.2 * size, 0.06);
    } else {
      const corners = [
        [frame.minX, frame.minY],
        [frame.maxX, frame.maxY],
      ];
      this.view.fit(bounds(corners, ...boxes), size, 0.04);
    }
  }

  // -- drawing the curve --------------------------------------------------------------------

  local(e) {
    const rect = this.canvas.getBoundingClientRect();
    return [e.clientX - rect.left, e.clientY - rect.top];
  }

  pointerDown(e) {
    if (e.button !== undefined && e.button > 0) return;
    if (this.drawing !== null || this.boxing !== null) return; // one finger draws
    const world = this.view.toWorld(...this.local(e));
    if (this.constraints && this.constraints.press(world, this.view)) {
      this.canvas.setPointerCapture(e.pointerId);
      this.boxing = e.pointerId;
      return;
    }
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
    if (e.pointerId === this.boxing) this.constraints.drag(this.view.toWorld(...this.local(e)));
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
    if (e.pointerId === this.boxing) {
      this.boxing = null;
      this.constraints.release();
    }
    if (e.pointerId !== this.drawing) return;
    this.drawing = null;
    this.say(`${this.points.length} points drawn: press “Find mechanisms”.`);
    this.paint();
  }

  clear() {
    this.runs += 1;
    this.stop();
    this.points = [];
    this.frameBox = UNIT;
    this.results = [];
    this.renderResults();
    this.fitView();
    this.say("");
    this.paint();
  }

  /** A curve opened from a drawing's file (`points` in its own units): drawn, and shown
   * whole; an open one is matched as part of a curve. */
  openCurve(points, closed, name) {
    this.runs += 1;
    this.stop();
    this.results = [];
    this.renderResults();
    this.points = points;
    this.frameBox = bounds(points);
    if (this.ui.partial) this.ui.partial.checked = !closed;
    this.fitView();
    const kind = closed ? "a closed curve" : "an open curve (matched as part of a path)";
    this.say(`${name}: ${points.length} points of ${kind}; press “Find mechanisms” or “Synthesize”.`);
    this.paint();
  }

  /** A retrieval's options beyond the curve: the most joints. */
  retrievalOptions() {
    const joints = this.ui.maxJoints ? this.ui.maxJoints.valueAsNumber : NaN;
    return Number.isFinite(joints) ? { max_joints: joints } : {};
  }

  /** The synthesis's options as the page sets them: joints, front, timing, partial,
   * constraints. */
  synthesisOptions() {
    const { front, timed, partial } = this.ui;
    const options = this.retrievalOptions();
    if (front && front.checked) options.front = true;
    if (timed && timed.checked) options.timing = true;
    if (partial && partial.checked) options.partial = true;
    const constraints = this.constraints ? this.constraints.body() : null;
    if (constraints) options.constraints = constraints;
    return options;
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
      ...(Number.isFinite(floor) && floor >= 0 ? { min_transmission: floor } : {}),
    };
    const options = synthesize ? this.synthesisOptions() : this.retrievalOptions();
    const what = synthesize ? "Synthesis" : "Retrieval";
    const buttons = [this.ui.retrieve, this.ui.synthesize].filter(Boolean);
    buttons.forEach((button) => (button.disabled = true));
    this.say(synthesize ? "Searching, then refining (a few seconds)…" : "Searching…");
    this.live = [];
    const run = ++this.runs; // a new drawing or search makes this one's progress stale
    try {
      const answer = synthesize
        ? await postJsonLines("/api/synthesize", { ...body, ...options, stream: true }, (line) => {
            if (run === this.runs) this.showProgress(line);
          })
        : await postJson("/api/retrieve", { ...body, ...options });
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
      this.front = synthesize && Boolean(this.ui.front && this.ui.front.checked);
      this.renderResults();
      this.showUnmet(answer.data.unmet);
      const count = this.results.length;
      const took = `${synthesize ? "synthesis" : "search"} ${answer.data.took_ms.toFixed(0)} ms`;
      const trip = `round trip ${answer.ms.toFixed(0)} ms`;
      const found = this.front
        ? `A front of ${count}, simplest first (${took}, ${trip}).`
        : `${count} mechanisms, best first (${took}, ${trip}).`;
      if (synthesize && count) {
        // A synthesis ends on its best mechanism (the front's most accurate), animating.
        await this.choose(bestOf(this.results), `${found} `);
        return;
      }
      this.say(
        count
          ? `${found} Choose one to watch it trace your curve.`
          : answer.data.unmet
            ? "No mechanism meets the constraints: loosen the one named below."
            : body.min_transmission
              ? `No curated path keeps a transmission angle of ${floor}°: lower it.`
              : "No curated paths to compare with: the dataset is empty.",
        Boolean(answer.data.unmet),
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

  /** What the constraints' refusal says: which one, and by how much the best candidate
   * misses it (nothing when `unmet` is absent). */
  showUnmet(unmet) {
    const shown = this.ui.unmet;
    if (!shown) return;
    shown.hidden = !unmet;
    if (!unmet) return;
    shown.dataset.constraint = String(unmet.constraint);
    shown.dataset.by = String(unmet.by);
    shown.textContent =
      `No candidate meets the constraint “${unmet.constraint}”: the best misses it by ` +
      `${Number(unmet.by).toPrecision(3)} (in the drawing's units, or the ratio for ` +
      "max_link_ratio).";
  }

  renderResults() {
    const list = this.ui.list;
    list.replaceChildren();
    if (this.ui.frontTable) {
      // A front is a table of joints against chamfer; anything else, the list.
      renderFront(this.ui.frontTable, this.front ? this.results : [], (i) => this.choose(i));
      list.hidden = Boolean(this.front && this.results.length);
    }
    if (this.ui.unmet) this.ui.unmet.hidden = true;
    this.results.forEach((result, i) => {
      const item = document.createElement("li");
      item.dataset.testid = "result";
      item.dataset.chamfer = String(result.chamfer);
      if (typeof result.n_joints === "number") item.dataset.joints = String(result.n_joints);
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
      const n = result.n_joints ?? result.mechanism.node_types.length;
      const timed = typeof result.timed_error === "number";
      // A synthesis result has no stored joint: it says what refinement gained instead.
      meta.textContent =
        result.retrieved_chamfer === undefined
          ? ` · mechanism ${result.mechanism_id}, joint ${result.joint} ` +
            `(${n} joints after reduction)` +
            (typeof angle === "number" ? `, least transmission ${angle.toFixed(1)}°` : "")
          : ` · ${n} joints, refined from ${result.retrieved_chamfer.toPrecision(4)}` +
            (timed ? `, timed error ${result.timed_error.toPrecision(4)}` : "") +
            `, from mechanism ${result.mechanism_id}`;
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
    if (this.ui.frontTable) markFront(this.ui.frontTable, this.front ? i : -1);
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
    const joints = typeof result.n_joints === "number" ? `, ${result.n_joints} joints` : "";
    const error = result.timed_error;
    const timed = typeof error === "number" ? `, timed error ${error.toPrecision(4)}` : "";
    this.say(
      `${lead}Result #${i + 1}: joint ${result.mechanism_joint} (thick) traces your curve ` +
        `(grey) with chamfer ${result.chamfer.toPrecision(4)}${timed}${joints}.`,
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
    if (this.constraints) this.constraints.paint(ctx, view);
    if (!this.chosen) return;
    const { result, trajectories } = this.chosen;
    const mech = result.mechanism;
    const t = Math.floor(this.frame);
    drawPaths(ctx, view, mech, trajectories, { emphasize: result.mechanism_joint });
    const pose = trajectories.map((path) => path[t]);
    drawMechanism(ctx, view, mech, pose, { selected: result.mechanism_joint, labels: false });
  }
}

/** The index of the result of least chamfer. */
function bestOf(results) {
  return results.reduce((best, r, i) => (r.chamfer < results[best].chamfer ? i : best), 0);
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
