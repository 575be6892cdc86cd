// The editor: build a mechanism with the J-operator, drag its joints, and watch it move.
//
// The server is the one source of truth: every change is simulated by POST /api/simulate (the
// same engine as links_ray.simulate), and the topology's degree of freedom and dyadic
// solvability come from POST /api/analyze (the engine's own checks). Requests are coalesced so
// that at most one of each kind is in flight; a drag shows each answer as it arrives.

import { Latest, explain, postJson } from "./api.js";
import {
  addGround,
  addJoint,
  clone,
  links,
  opening,
  removeJoint,
  starter,
  toggleLink,
  topologyKey,
} from "./mechanism.js";
import {
  COLORS,
  View,
  bounds,
  drawCross,
  drawGrid,
  drawMechanism,
  drawPaths,
  trackSize,
} from "./view.js";

export const STEPS = 200;
const STEPS_PER_SECOND = 50; // one crank turn in four seconds
const HISTORY_LIMIT = 500;
const LATENCY_WINDOW = 500;

const HINTS = {
  move: () => "Drag a joint to move it; drag empty space to pan; wheel or pinch to zoom.",
  joint: (picks) =>
    [
      "Add joint (J-operator): pick the first joint the new joint links to.",
      `Add joint: joint ${picks[0]} picked; pick the second joint.`,
      `Add joint: joints ${picks[0]} and ${picks[1]} picked; click where the new joint goes.`,
    ][picks.length],
  ground: () => "Add ground: click where the fixed joint goes.",
  link: (picks) =>
    picks.length
      ? `Link: joint ${picks[0]} picked; pick the other end (an existing link is removed).`
      : "Link: pick two joints to add or remove the link between them.",
  delete: () => "Delete: click a joint (not the crank's 0 or 1) or a link.",
};
// Until the first action on the opening four-bar: what to try first.
const WELCOME = "Drag joint 4 to reshape its curve, or press New to build your own.";

function fields(mech) {
  return { adjacency: mech.adjacency, node_types: mech.node_types, positions: mech.positions };
}

function median(values) {
  const sorted = values.slice().sort((a, b) => a - b);
  return sorted.length ? sorted[Math.floor((sorted.length - 1) / 2)] : NaN;
}

export class Editor {
  /**
   * `ui` holds the page's elements (hint, play, crank, crankValue, dof, solvable, status,
   * latency, rules, lock, undo, redo, tools); `notify(message, source)` shows a page-level error.
   */
  constructor({ canvas, ui, notify }) {
    this.canvas = canvas;
    this.ui = ui;
    this.notify = notify;
    this.view = new View();
    this.history = [opening()];
    this.at = 0;
    this.mech = this.history[0];
    this.version = 0; // bumps on every change to `mech`, drags included
    this.tool = "move";
    this.picks = [];
    this.selected = -1;
    this.hover = null; // world point under the pointer, for the J-operator's preview
    this.gesture = null; // the drag, pan or pinch under way
    this.pointers = new Map(); // pointer id -> screen point, for pinching
    this.message = null; // a refusal to show in the hint line until the next action
    this.welcome = WELCOME; // shown in the hint line until the first action
    this.autoplay = true; // play once the mechanism shown first has simulated
    this.drawnPaths = null; // screen points of each joint's path as last painted (null: none)
    this.sim = { version: -1, state: "pending", trajectories: null, lock: null, problem: null };
    this.queued = null; // the pose last sent to be simulated (JSON of its fields)
    this.analysis = null;
    this.analysisKey = null;
    this.step = 0;
    this.playing = false;
    this.latencies = []; // /api/simulate round trips, ms
    this.changeListeners = []; // called with the new version after every change
    this.simulations = new Latest((job) => this.runSimulation(job));
    this.analyses = new Latest((job) => this.runAnalysis(job));
    this.fitted = false;
    this.ctx = trackSize(canvas, (width, height) => {
      this.view.width = width;
      this.view.height = height;
      if (!this.fitted && width > 1) {
        this.fit(0.3); // room around the mechanism to add joints
        this.fitted = true;
      }
      this.draw();
    });
    this.listen();
    this.changed();
    // Once its paths are known, show the opening mechanism large, with room around it.
    this.refit = this.version;
    this.refitExtent = 0.3;
  }

  // -- changes and history ------------------------------------------------------------------

  /** Make `mech` current as a new undo step. */
  set(mech) {
    this.history = this.history.slice(0, this.at + 1);
    this.history.push(mech);
    if (this.history.length > HISTORY_LIMIT) this.history.shift();
    this.at = this.history.length - 1;
    this.mech = mech;
    this.changed();
  }

  /**
   * Replace the mechanism (an import, a share link or a retrieval result) and show it whole,
   * at its starting pose; with `play`, it plays once simulated, if it turns fully.
   */
  load(mech, { play = false } = {}) {
    this.picks = [];
    this.selected = -1;
    this.welcome = null;
    this.setPlaying(false);
    this.autoplay = play;
    this.set(clone(mech));
    this.fit();
    this.refit = this.version; // fit again once its paths are known, unless the user moves the view
    this.refitExtent = 0.1;
  }

  undo() {
    if (this.at === 0) return;
    this.at -= 1;
    this.mech = this.history[this.at];
    this.changed();
  }

  redo() {
    if (this.at >= this.history.length - 1) return;
    this.at += 1;
    this.mech = this.history[this.at];
    this.changed();
  }

  /** After any change: simulate the new geometry, analyse a new topology, redraw. */
  changed() {
    this.version += 1;
    const n = this.mech.node_types.length;
    this.picks = this.picks.filter((j) => j < n);
    if (this.selected >= n) this.selected = -1;
    this.step = 0; // edits apply to the starting pose: show it
    // A pose already sent is not sent again (a drag's drop sets the pose of its last move):
    // its answer, come or coming, is for this version too. A failed one is retried.
    const pose = JSON.stringify(fields(this.mech));
    const answered = this.sim.pose === pose;
    if (pose === this.queued && answered && this.sim.state !== "error") {
      this.sim = { ...this.sim, version: this.version };
      this.showSimulation();
    } else if (pose !== this.queued || answered) {
      this.queued = pose;
      this.simulations.push({ version: this.version, pose });
    }
    const key = topologyKey(this.mech);
    if (key !== this.analysisKey) {
      this.analysisKey = key;
      this.analyses.push({ key, mech: this.mech });
    }
    this.canvas.dataset.version = String(this.version);
    this.ui.undo.disabled = this.at === 0;
    this.ui.redo.disabled = this.at >= this.history.length - 1;
    this.showHint();
    this.showStep();
    this.draw();
    for (const listener of this.changeListeners) listener(this.version);
  }

  /** Call `listener(version)` after every change to the mechanism, drags included. */
  whenChanged(listener) {
    this.changeListeners.push(listener);
  }

  /** True once every change has been simulated and analysed. */
  get idle() {
    return (
      this.simulations.idle &&
      this.analyses.idle &&
      this.sim.version === this.version &&
      this.analysis !== null &&
      this.analysis.key === this.analysisKey
    );
  }

  // -- talking to the server ----------------------------------------------------------------

  async runSimulation({ version, pose }) {
    const mech = JSON.parse(pose);
    const body = { ...mech, steps: STEPS };
    let result;
    try {
      const answer = await postJson("/api/simulate", body);
      this.latencies.push(answer.ms);
      if (this.latencies.length > LATENCY_WINDOW) this.latencies.shift();
      if (answer.status === 200 && answer.data && answer.data.trajectories) {
        result = { state: "ok", trajectories: answer.data.trajectories, lock: null, problem: null };
      } else if (answer.status === 422 && answer.data && answer.data.error === "locking") {
        result = await this.lockDetails(body, answer.data);
      } else {
        result = { state: "error", trajectories: null, lock: null, problem: explain(answer) };
      }
      this.notify("", "network");
    } catch (err) {
      result = { state: "error", trajectories: null, lock: null, problem: err.message };
      this.notify(`Simulation failed: ${err.message}`, "network");
    }
    // Still the pose shown (the last one sent): the answer is for the current version too.
    const current = pose === this.queued ? this.version : version;
    this.sim = { version: current, pose, n: mech.node_types.length, ...result };
    this.showSimulation();
  }

  /** /api/simulate says where it locks; /api/analyze adds the paths up to that step. */
  async lockDetails(body, locking) {
    const lock = { step: locking.step, node: locking.node, angle: (360 * locking.step) / STEPS };
    const answer = await postJson("/api/analyze", body);
    if (answer.status !== 200 || !answer.data) {
      return { state: "locking", trajectories: null, lock, problem: explain(answer) };
    }
    return { state: "locking", trajectories: answer.data.trajectories || null, lock, problem: null };
  }

  async runAnalysis({ key, mech }) {
    let analysis;
    try {
      const answer = await postJson("/api/analyze", {
        adjacency: mech.adjacency,
        node_types: mech.node_types,
      });
      analysis = answer.status === 200 && answer.data ? answer.data : { error: explain(answer) };
    } catch (err) {
      analysis = { error: err.message };
    }
    analysis.key = key;
    this.analysis = analysis;
    if (key === this.analysisKey) this.showAnalysis();
  }

  // -- what the panel says ------------------------------------------------------------------

  showHint() {
    const hint = this.ui.hint;
    hint.textContent = this.message || this.welcome || HINTS[this.tool](this.picks);
    hint.classList.toggle("bad", Boolean(this.message));
    for (const button of this.ui.tools) {
      button.setAttribute("aria-pressed", String(button.dataset.tool === this.tool));
    }
  }

  /** Say why an edit was refused, in the hint line, until the next action. */
  refuse(message) {
    this.message = message;
    this.showHint();
  }

  showSimulation() {
    const { status, lock, latency } = this.ui;
    const sim = this.sim;
    status.classList.toggle("good", sim.state === "ok");
    status.classList.toggle("bad", sim.state !== "ok");
    if (sim.state === "ok") {
      status.textContent = `a full crank turn, ${STEPS} steps, every joint assembles`;
    } else if (sim.state === "locking") {
      status.textContent = `locks after ${sim.lock.angle.toFixed(1)}° of crank turn`;
    } else {
      status.textContent = `cannot simulate: ${sim.problem}`;
    }
    if (sim.state === "locking") {
      const parents = this.parentsOf(sim.lock.node);
      const why = parents
        ? `its links to joints ${parents[0]} and ${parents[1]} can no longer both be reached`
        : "it can no longer be assembled";
      lock.textContent =
        `Locks at crank angle ${sim.lock.angle.toFixed(1)}° (step ${sim.lock.step} of ` +
        `${STEPS}): joint ${sim.lock.node} is marked ✕ where ${why}.` +
        (sim.problem ? ` (No paths: ${sim.problem})` : "");
      lock.hidden = false;
    } else {
      lock.hidden = true;
    }
    const ms = this.latencies;
    if (ms.length) {
      latency.textContent =
        `/api/simulate ${ms[ms.length - 1].toFixed(0)} ms, ` +
        `median ${median(ms).toFixed(0)} ms over ${ms.length}`;
    }
    this.canvas.dataset.state = sim.state;
    this.canvas.dataset.simulated = String(sim.version);
    this.step = Math.min(this.step, Math.max(this.frames() - 1, 0));
    this.showStep();
    if (this.refit === sim.version) {
      this.refit = null;
      this.fit(this.refitExtent);
    }
    if (this.autoplay && sim.version === this.version) {
      this.autoplay = false;
      if (sim.state === "ok") this.setPlaying(true);
    }
    this.draw();
  }

  showAnalysis() {
    const { dof, solvable, rules } = this.ui;
    const a = this.analysis;
    if (a.error) {
      for (const element of [dof, solvable, rules]) {
        element.textContent = `unknown: ${a.error}`;
        element.className = "bad";
      }
      return;
    }
    dof.textContent = `${a.dof} (2 x ${a.moving} moving joints - ${a.links} links)`;
    dof.className = a.dof === 1 ? "good" : "bad";
    solvable.textContent = a.solvable ? "yes" : `no: ${a.problem}`;
    solvable.className = a.solvable ? "good" : "bad";
    if (!a.solvable) {
      rules.textContent = "not checked until it is solvable";
      rules.className = "";
    } else if (a.dataset_rules.length) {
      // The rules are those of a stored mechanism; smaller ones are still retrieved, as the
      // joints a stored mechanism's path needs.
      rules.textContent = `unlike the dataset's mechanisms: ${a.dataset_rules.join("; ")}`;
      rules.className = "";
    } else {
      rules.textContent = "its topology could be in the dataset";
      rules.className = "good";
    }
    this.canvas.dataset.analyzed = a.key === this.analysisKey ? "current" : "stale";
    if (this.sim.state === "locking") this.showSimulation(); // the lock text names parents
  }

  /** The two joints `joint` is solved from, per the current analysis (null if unknown). */
  parentsOf(joint) {
    const row = this.analysis && this.analysis.order && this.analysis.order.find((r) => r[0] === joint);
    return row ? [row[1], row[2]] : null;
  }

  // -- playback -----------------------------------------------------------------------------

  /** The simulated paths if they belong to the current joints (they lag during a drag). */
  trajectories() {
    const t = this.sim.trajectories;
    return t && t.length === this.mech.node_types.length && t[0].length ? t : null;
  }

  frames() {
    const t = this.trajectories();
    return t ? t[0].length : 1;
  }

  setPlaying(on) {
    this.playing = on && this.frames() > 1;
    this.ui.play.textContent = this.playing ? "Pause" : "Play";
    this.loop = (this.loop || 0) + 1; // a newer loop retires the older one
    if (!this.playing) return;
    const loop = this.loop;
    let last = performance.now();
    let position = this.step;
    const tick = (now) => {
      if (!this.playing || loop !== this.loop) return;
      // rAF's timestamp can precede `last`, taken when the loop started: never step back.
      position = (position + (Math.max(now - last, 0) / 1000) * STEPS_PER_SECOND) % this.frames();
      last = now;
      if (!this.gesture) {
        this.step = Math.floor(position);
        this.showStep();
        this.paint();
      }
      requestAnimationFrame(tick);
    };
    requestAnimationFrame(tick);
  }

  setStep(step) {
    this.step = Math.max(0, Math.min(step, this.frames() - 1));
    this.showStep();
    this.draw();
  }

  showStep() {
    const { crank, crankValue, play } = this.ui;
    crank.max = String(Math.max(this.frames() - 1, 0));
    crank.value = String(this.step);
    crank.disabled = this.frames() < 2;
    play.disabled = this.frames() < 2;
    crankValue.textContent = `${((360 * this.step) / STEPS).toFixed(1)}°`;
    this.canvas.dataset.step = String(this.step);
  }

  /** Joint positions as drawn: the starting pose, or the simulated pose at the crank step. */
  pose() {
    const t = this.trajectories();
    if (!t || this.step === 0 || (this.gesture && this.gesture.kind === "drag")) {
      return this.mech.positions;
    }
    return t.map((path) => path[Math.min(this.step, path.length - 1)]);
  }

  // -- drawing ------------------------------------------------------------------------------

  /** Show the mechanism and its paths whole, at least `minExtent` world units across. */
  fit(minExtent = 0.1) {
    const b = bounds(this.mech.positions, ...(this.trajectories() || []));
    if (b) this.view.fit(b, minExtent);
    this.draw();
  }

  /** Redraw on the next frame; many changes in one frame cost one paint. */
  draw() {
    if (this.paintQueued) return;
    this.paintQueued = true;
    requestAnimationFrame(() => {
      this.paintQueued = false;
      this.paint();
    });
  }

  paint() {
    const { ctx, view, mech } = this;
    ctx.clearRect(0, 0, view.width, view.height);
    drawGrid(ctx, view);
    const trajectories = this.trajectories();
    const locked = this.sim.state === "locking" ? this.sim.lock : null;
    this.drawnPaths = drawPaths(ctx, view, mech, trajectories, { full: !locked });
    if (locked && this.sim.n === mech.node_types.length) this.paintLock(locked, trajectories);
    const pose = this.pose();
    if (this.tool === "joint" && this.picks.length === 2 && this.hover) this.paintPreview(pose);
    drawMechanism(ctx, view, mech, pose, { picked: this.picks, selected: this.selected });
  }

  /** Where it locks: the last pose that assembles, faded, and a cross on the joint that fails. */
  paintLock(lock, trajectories) {
    const { ctx, view, mech } = this;
    const last = lock.step - 1;
    let at = mech.positions[lock.node];
    if (trajectories && last >= 0) {
      const pose = trajectories.map((path) => path[last]);
      if (this.step !== last) drawMechanism(ctx, view, mech, pose, { labels: false, fade: true });
      at = pose[lock.node];
    }
    drawCross(ctx, view, at);
    const [sx, sy] = view.toScreen(at);
    ctx.save();
    ctx.fillStyle = COLORS.lock;
    ctx.font = "bold 12px system-ui, sans-serif";
    ctx.fillText(`locks at ${lock.angle.toFixed(1)}°`, sx + 12, sy + 16);
    ctx.restore();
  }

  /** Dashed lines from the two picked joints to where the new joint would go. */
  paintPreview(pose) {
    const { ctx, view } = this;
    const [hx, hy] = view.toScreen(this.hover);
    ctx.save();
    ctx.setLineDash([5, 5]);
    ctx.strokeStyle = COLORS.pick;
    ctx.lineWidth = 2;
    ctx.beginPath();
    for (const j of this.picks) {
      const [sx, sy] = view.toScreen(pose[j]);
      ctx.moveTo(sx, sy);
      ctx.lineTo(hx, hy);
    }
    ctx.stroke();
    ctx.restore();
  }

  // -- pointer and keyboard -----------------------------------------------------------------

  listen() {
    const c = this.canvas;
    c.addEventListener("pointerdown", (e) => this.pointerDown(e));
    c.addEventListener("pointermove", (e) => this.pointerMove(e));
    c.addEventListener("pointerup", (e) => this.pointerUp(e));
    c.addEventListener("pointercancel", (e) => this.pointerUp(e));
    c.addEventListener("pointerleave", () => {
      this.hover = null;
      this.draw();
    });
    c.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault(); // zoom the drawing, not the page
        this.refit = null;
        const [sx, sy] = this.local(e);
        this.view.zoomAt(sx, sy, Math.exp(-e.deltaY * 0.0015));
        this.draw();
      },
      { passive: false },
    );
  }

  local(e) {
    const rect = this.canvas.getBoundingClientRect();
    return [e.clientX - rect.left, e.clientY - rect.top];
  }

  /** The joint drawn under screen point `p`, or -1; fingers get a larger target. */
  hitJoint(p, pointerType) {
    const reach = pointerType === "touch" ? 22 : 12;
    let best = -1;
    let bestDistance = reach;
    this.pose().forEach((q, j) => {
      const [sx, sy] = this.view.toScreen(q);
      const d = Math.hypot(sx - p[0], sy - p[1]);
      if (d <= bestDistance) {
        best = j;
        bestDistance = d;
      }
    });
    return best;
  }

  /** The link drawn under screen point `p` as [i, j], or null. */
  hitLink(p, pointerType) {
    const reach = pointerType === "touch" ? 14 : 7;
    const pose = this.pose();
    for (const [i, j] of links(this.mech)) {
      const [ax, ay] = this.view.toScreen(pose[i]);
      const [bx, by] = this.view.toScreen(pose[j]);
      const length2 = (bx - ax) ** 2 + (by - ay) ** 2 || 1;
      const t = Math.max(0, Math.min(1, ((p[0] - ax) * (bx - ax) + (p[1] - ay) * (by - ay)) / length2));
      if (Math.hypot(ax + t * (bx - ax) - p[0], ay + t * (by - ay) - p[1]) <= reach) return [i, j];
    }
    return null;
  }

  pointerDown(e) {
    if (e.button !== undefined && e.button > 0) return; // primary button or touch only
    this.canvas.focus();
    this.canvas.setPointerCapture(e.pointerId);
    const p = this.local(e);
    this.pointers.set(e.pointerId, p);
    this.message = null;
    this.welcome = null;
    if (this.pointers.size === 2) {
      this.startPinch();
      return;
    }
    const hit = this.hitJoint(p, e.pointerType);
    const world = this.view.toWorld(p[0], p[1]);
    try {
      if (this.tool === "move") this.pressMove(e, hit, world, p);
      else if (this.tool === "joint") this.pressJoint(hit, world);
      else if (this.tool === "ground") this.pressGround(hit, world);
      else if (this.tool === "link") this.pressLink(hit);
      else if (this.tool === "delete") this.pressDelete(hit, p, e.pointerType);
    } catch (err) {
      this.message = err.message; // an edit the model refuses, e.g. deleting the crank
    }
    this.showHint();
    this.draw();
  }

  pressMove(e, hit, world, p) {
    if (hit < 0) {
      this.selected = -1;
      this.refit = null;
      this.gesture = { kind: "pan", id: e.pointerId, last: p };
      return;
    }
    this.selected = hit;
    // Drag a copy: the undo history keeps the pose from before the drag.
    const start = this.mech.positions[hit].slice();
    this.mech = clone(this.mech);
    this.gesture = { kind: "drag", id: e.pointerId, joint: hit, from: world, start, moved: false };
    this.gesture.resume = this.playing;
    this.setPlaying(false);
  }

  pressJoint(hit, world) {
    if (hit >= 0) {
      if (this.picks.includes(hit)) this.picks = this.picks.filter((j) => j !== hit);
      else if (this.picks.length < 2) this.picks.push(hit);
      else this.picks[1] = hit; // a third joint replaces the second pick
      return;
    }
    if (this.picks.length < 2) {
      this.message = "Pick two existing joints first, then click where the new joint goes.";
      return;
    }
    const [a, b] = this.picks;
    this.picks = [];
    this.set(addJoint(this.mech, a, b, world));
  }

  pressGround(hit, world) {
    if (hit >= 0) {
      this.message = `Joint ${hit} is there already: click on empty space.`;
      return;
    }
    this.set(addGround(this.mech, world));
  }

  pressLink(hit) {
    if (hit < 0) return;
    if (this.picks.includes(hit)) {
      this.picks = this.picks.filter((j) => j !== hit);
      return;
    }
    this.picks.push(hit);
    if (this.picks.length === 2) {
      const [a, b] = this.picks;
      this.picks = [];
      this.set(toggleLink(this.mech, a, b));
    }
  }

  pressDelete(hit, p, pointerType) {
    if (hit >= 0) {
      this.selected = -1;
      this.set(removeJoint(this.mech, hit));
      return;
    }
    const link = this.hitLink(p, pointerType);
    if (link) this.set(toggleLink(this.mech, link[0], link[1]));
  }

  startPinch() {
    if (this.gesture && this.gesture.kind === "drag") this.endDrag();
    const [a, b] = [...this.pointers.values()];
    this.gesture = { kind: "pinch", a, b };
  }

  pointerMove(e) {
    const p = this.local(e);
    if (this.pointers.has(e.pointerId)) this.pointers.set(e.pointerId, p);
    const g = this.gesture;
    if (!g) {
      this.hover = this.view.toWorld(p[0], p[1]);
      this.canvas.style.cursor = this.hitJoint(p, e.pointerType) >= 0 ? "grab" : "default";
      if (this.tool === "joint" && this.picks.length === 2) this.draw();
      return;
    }
    if (g.kind === "drag" && g.id === e.pointerId) {
      const world = this.view.toWorld(p[0], p[1]);
      // Move by the pointer's travel, so a joint grabbed off-centre does not jump.
      this.mech.positions[g.joint] = [
        g.start[0] + world[0] - g.from[0],
        g.start[1] + world[1] - g.from[1],
      ];
      g.moved = true;
      this.changed();
    } else if (g.kind === "pan" && g.id === e.pointerId) {
      this.view.panBy(p[0] - g.last[0], p[1] - g.last[1]);
      g.last = p;
      this.draw();
    } else if (g.kind === "pinch" && this.pointers.size === 2) {
      const [a, b] = [...this.pointers.values()];
      const before = [(g.a[0] + g.b[0]) / 2, (g.a[1] + g.b[1]) / 2];
      const after = [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2];
      const ratio = Math.hypot(a[0] - b[0], a[1] - b[1]) / (Math.hypot(g.a[0] - g.b[0], g.a[1] - g.b[1]) || 1);
      this.view.panBy(after[0] - before[0], after[1] - before[1]);
      this.view.zoomAt(after[0], after[1], ratio);
      g.a = a;
      g.b = b;
      this.draw();
    }
  }

  pointerUp(e) {
    this.pointers.delete(e.pointerId);
    const g = this.gesture;
    if (!g) return;
    if (g.kind === "drag" && g.id === e.pointerId) this.endDrag();
    else if (g.kind === "pan" && g.id === e.pointerId) this.gesture = null;
    else if (g.kind === "pinch" && this.pointers.size < 2) this.gesture = null;
  }

  endDrag() {
    const g = this.gesture;
    this.gesture = null;
    if (g.moved) this.set(this.mech); // the whole drag is one undo step
    else this.mech = this.history[this.at];
    if (g.resume) this.setPlaying(true);
    this.draw();
  }

  setTool(tool) {
    this.tool = tool;
    this.picks = [];
    this.message = null;
    this.welcome = null;
    this.showHint();
    this.draw();
  }

  /** Keyboard shortcuts; returns true when the key was used. */
  key(e) {
    const mod = e.ctrlKey || e.metaKey;
    const key = e.key.toLowerCase();
    if (mod && key === "z") {
      if (e.shiftKey) this.redo();
      else this.undo();
    } else if (mod && key === "y") {
      this.redo();
    } else if (mod) {
      return false;
    } else if ((key === "delete" || key === "backspace") && this.selected >= 0) {
      try {
        this.set(removeJoint(this.mech, this.selected));
        this.selected = -1;
      } catch (err) {
        this.refuse(err.message);
      }
    } else if (key === "escape") {
      this.setTool(this.tool);
    } else if (key === " ") {
      this.setPlaying(!this.playing);
    } else if ({ v: 1, j: 1, g: 1, l: 1, d: 1 }[key]) {
      this.setTool({ v: "move", j: "joint", g: "ground", l: "link", d: "delete" }[key]);
    } else {
      return false;
    }
    return true;
  }

  /** A fresh start: the crank and one ground joint. */
  reset() {
    this.load(starter());
    this.refit = null;
    this.fit(0.5); // room around it to add joints
  }

  /** The current mechanism's fields (a copy). */
  current() {
    return clone(this.mech);
  }
}
