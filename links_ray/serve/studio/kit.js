// Build: the editor's mechanism as a kit of printable parts (POST /api/kit), shown in 3D and
// turning with the crank, with its layer plan in the editor's analysis and its files to
// download.
//
// The server plans the kit once, at the starting pose: its bill of materials says which layer
// each bar is on and how long each pin and spacer is. Where the joints are at each crank step
// comes from the same simulation the editor animates (POST /api/simulate), taken into the
// kit's frame as the bill says: (p - origin) * mm_per_unit. So the bars turn exactly as the
// mechanism does, and a kit costs one plan, not one a frame.

import { explain, postForFile, postJson } from "./api.js";
import { STEPS } from "./editor.js";
import { download } from "./files.js";

const STEPS_PER_SECOND = 50; // as the editor: one crank turn in four seconds

/** What a layer plan says about itself, in words: how many layers, and whether fewer exist. */
export function layerWords(bom) {
  const count = `${bom.layers} layer${bom.layers === 1 ? "" : "s"}`;
  if (bom.optimal) return `${count}, proven fewest`;
  const why = {
    "work limit": "the search spent its counted work",
    "time limit": "the search hit its time limit",
  }[bom.status] ?? "a heuristic's plan";
  return `${count}, perhaps not the fewest: at least ${bom.lower_bound} (${why})`;
}

export class KitView {
  /**
   * `ui`: build (the button), layers (the analysis line), panel, status, canvas, play, crank,
   * crankValue, explode, explodeValue, close, downloads {zip, glb, bom}, and the sizes
   * crankMm, barWidth, clearance, layerThickness, base; `editor` has the mechanism and its
   * simulation; `notify(message, source)` shows a page-level error.
   */
  constructor({ ui, editor, notify }) {
    this.ui = ui;
    this.editor = editor;
    this.notify = notify;
    this.scene = null; // a KitScene once a kit is first shown
    this.kit = null; // {bom, body, version, joints: per step, per joint, [x, y] in mm}
    this.runs = 0; // builds started: only the latest one's answer is shown
    this.building = 0;
    this.downloading = 0;
    this.step = 0;
    this.playing = false;
    this.loop = 0;
    editor.whenChanged((version) => this.mechanismChanged(version));
    ui.build.addEventListener("click", () => this.build());
    ui.play.addEventListener("click", () => this.setPlaying(!this.playing));
    ui.crank.addEventListener("input", () => {
      this.setPlaying(false); // the user has taken the crank
      this.setStep(ui.crank.valueAsNumber);
    });
    ui.explode.addEventListener("input", () => this.pose());
    ui.close.addEventListener("click", () => this.close());
    ui.downloads.zip.addEventListener("click", () => this.downloadFile("zip"));
    ui.downloads.glb.addEventListener("click", () => this.downloadFile("glb"));
    ui.downloads.bom.addEventListener("click", () => this.downloadBill());
    this.showKitControls();
  }

  get idle() {
    return this.building === 0 && this.downloading === 0;
  }

  /** The spacing added between layers, in mm: the slider counts layer pitches. */
  get explodeMm() {
    const bom = this.kit && this.kit.bom;
    if (!bom) return 0;
    return this.ui.explode.valueAsNumber * (bom.layer_thickness_mm + bom.layer_gap_mm);
  }

  /** The request's sizes as the page sets them; an empty field is left to the server's
   * default. */
  sizes() {
    const { crankMm, barWidth, clearance, layerThickness, base } = this.ui;
    const body = { ground_on_base: base.checked };
    for (const [field, input] of [
      ["crank_mm", crankMm],
      ["bar_width_mm", barWidth],
      ["clearance_mm", clearance],
      ["layer_thickness_mm", layerThickness],
    ]) {
      if (input.value.trim() !== "") body[field] = Number(input.value);
    }
    return body;
  }

  say(text, bad = false) {
    this.ui.status.textContent = text;
    this.ui.status.classList.toggle("bad", bad);
  }

  /** The analysis line: the layer plan, or why there is none. */
  line(text, state) {
    const layers = this.ui.layers;
    layers.textContent = text;
    layers.className = state === "ok" ? "good" : state === "bad" ? "bad" : "";
  }

  // -- building -----------------------------------------------------------------------------

  /** Plan the editor's mechanism as a kit and show it. */
  async build() {
    const mech = this.editor.current();
    const version = this.editor.version;
    const body = { ...mech, ...this.sizes() };
    const run = ++this.runs;
    this.ui.panel.hidden = false;
    this.building += 1;
    this.ui.build.disabled = true;
    this.say("Planning the layers and the parts…");
    this.line("planning…", "");
    this.ui.panel.dataset.state = "building";
    try {
      const [answer, trajectories] = await Promise.all([
        postJson("/api/kit", { ...body, format: "bom" }),
        this.trajectoriesOf(mech, version),
      ]);
      if (run !== this.runs) return;
      if (answer.status !== 200 || !answer.data || !Array.isArray(answer.data.links)) {
        this.refuse(answer);
        return;
      }
      await this.show(answer.data, body, version, trajectories);
    } catch (err) {
      if (run !== this.runs) return;
      this.line(`not planned: ${err.message}`, "bad");
      this.say(`The kit could not be made: ${err.message}`, true);
      this.ui.panel.dataset.state = "failed";
    } finally {
      this.building -= 1;
      this.ui.build.disabled = false;
    }
  }

  /** The editor's paths when they are of this very mechanism; else the server's. */
  async trajectoriesOf(mech, version) {
    const sim = this.editor.sim;
    if (sim.version === version && sim.state === "ok") return this.editor.trajectories();
    const answer = await postJson("/api/simulate", { ...mech, steps: STEPS });
    return answer.status === 200 && answer.data ? answer.data.trajectories : null;
  }

  /** A refusal: 422 says why no stacking exists (or that it locks), in the analysis line. */
  refuse(answer) {
    this.forget();
    const reason = answer.data && answer.data.error ? answer.data.error : explain(answer);
    if (answer.status === 422) {
      this.line(`cannot be built: ${reason}`, "bad");
      this.say(`No kit: ${reason}`, true);
      this.ui.panel.dataset.state = "refused";
    } else {
      this.line(`not planned: ${explain(answer)}`, "bad");
      this.say(`The kit could not be made: ${explain(answer)}`, true);
      this.ui.panel.dataset.state = "failed";
    }
  }

  /** Show the kit of `bom`, its joints moving along `trajectories` (null: standing still). */
  async show(bom, body, version, trajectories) {
    const [ox, oy] = bom.origin;
    const s = bom.mm_per_unit;
    const start = bom.joints.map((j) => [j.x_mm, j.y_mm]);
    const joints = trajectories
      ? trajectories[0].map((_, t) =>
          trajectories.map((path) => [(path[t][0] - ox) * s, (path[t][1] - oy) * s]),
        )
      : [start];
    this.kit = { bom, body, version, joints };
    this.line(layerWords(bom), "ok");
    const drawn = await this.ensureScene();
    this.showKitControls(); // the files can be had even where nothing can be drawn
    if (drawn) {
      this.scene.setKit(bom);
      this.step = 0;
      this.pose();
      this.scene.frame(this.box());
      const n = bom.links.length + bom.pins.length + bom.spacers.length + (bom.base ? 1 : 0);
      const base = bom.base ? ", a base plate" : "";
      this.say(
        `${layerWords(bom)}: ${bom.links.length} bars, ${bom.pins.length} pins, ` +
          `${bom.spacers.length} spacers${base} (${n} parts placed, ${bom.parts.length} files), ` +
          `crank ${bom.crank_mm} mm; planned in ${bom.took_ms.toFixed(0)} ms.`,
      );
      this.ui.panel.dataset.state = "shown";
      this.ui.canvas.dataset.parts = String(n);
      this.ui.panel.scrollIntoView({ behavior: "smooth", block: "nearest" });
      this.setPlaying(joints.length > 1);
    }
    this.mechanismChanged(this.editor.version); // edited while the kit was planned
  }

  /** The 3D scene, made on first use (three.js loads then); false if it cannot be. */
  async ensureScene() {
    if (this.scene) return true;
    try {
      const { KitScene } = await import("./kitscene.js");
      this.scene = new KitScene(this.ui.canvas);
      return true;
    } catch (err) {
      this.say(`The kit is planned, but it cannot be drawn here: ${err.message}`, true);
      this.ui.panel.dataset.state = "failed";
      return false;
    }
  }

  /** What the view must hold: every joint over the turn, and the stack exploded. */
  box() {
    const { bom, joints } = this.kit;
    const min = [Infinity, Infinity, 0];
    const max = [-Infinity, -Infinity, 0];
    for (const pose of joints) {
      for (const [x, y] of pose) {
        min[0] = Math.min(min[0], x - bom.bar_width_mm);
        min[1] = Math.min(min[1], y - bom.bar_width_mm);
        max[0] = Math.max(max[0], x + bom.bar_width_mm);
        max[1] = Math.max(max[1], y + bom.bar_width_mm);
      }
    }
    const explode = this.explodeMm;
    min[2] = bom.base ? bom.base.z_mm[0] - explode : 0;
    max[2] = Math.max(...bom.pins.map((pin) => pin.z_mm[1] + explode * pin.layers[1]), 0);
    return { min, max };
  }

  /** The kit's parts at the current step and explode spacing. */
  pose() {
    if (!this.kit || !this.scene) return;
    const { joints } = this.kit;
    this.step = Math.max(0, Math.min(this.step, joints.length - 1));
    this.scene.pose(joints[this.step], this.explodeMm);
    const { crank, crankValue, explodeValue, canvas } = this.ui;
    crank.value = String(this.step);
    crankValue.textContent = `${((360 * this.step) / STEPS).toFixed(1)}°`;
    explodeValue.textContent = `+${this.explodeMm.toFixed(1)} mm`;
    canvas.dataset.step = String(this.step);
  }

  // -- playback and the mechanism's changes -------------------------------------------------

  setStep(step) {
    this.step = step;
    this.pose();
  }

  setPlaying(on) {
    this.playing = Boolean(on && this.kit && this.scene && this.kit.joints.length > 1);
    this.ui.play.textContent = this.playing ? "Pause" : "Play";
    this.loop += 1; // a newer loop retires the older one
    if (!this.playing) return;
    const loop = this.loop;
    let last = performance.now();
    let position = this.step;
    const tick = (now) => {
      if (!this.playing || loop !== this.loop) return;
      // rAF's timestamp can precede `last`, taken when the loop started: never step back.
      position =
        (position + (Math.max(now - last, 0) / 1000) * STEPS_PER_SECOND) % this.kit.joints.length;
      last = now;
      this.setStep(Math.floor(position));
      requestAnimationFrame(tick);
    };
    requestAnimationFrame(tick);
  }

  showKitControls() {
    const shown = Boolean(this.kit && this.scene);
    const { crank, play, explode, downloads } = this.ui;
    crank.max = String(shown ? this.kit.joints.length - 1 : 0);
    crank.disabled = !shown || this.kit.joints.length < 2;
    play.disabled = crank.disabled;
    explode.disabled = !shown;
    for (const button of Object.values(downloads)) button.disabled = !this.kit;
  }

  /** The editor's mechanism changed: the kit shown is of the one before. */
  mechanismChanged(version) {
    if (!this.kit || this.kit.version === version || this.kit.stale) return;
    this.kit.stale = true;
    this.line("changed since its kit was planned: press Build 3D", "");
    this.say(
      "The editor's mechanism has changed: this is the kit of the one before. Press Build 3D again.",
    );
  }

  /** No kit: a refusal, or a failure, leaves nothing to show or download. */
  forget() {
    this.setPlaying(false);
    this.kit = null;
    if (this.scene) this.scene.clear();
    this.showKitControls();
  }

  close() {
    this.setPlaying(false);
    this.ui.panel.hidden = true;
  }

  // -- downloads ----------------------------------------------------------------------------

  /** The kit shown, as the server makes it: "zip" (parts, bill, assembly) or "glb". */
  async downloadFile(format) {
    if (!this.kit) return;
    this.downloading += 1;
    try {
      const answer = await postForFile("/api/kit", { ...this.kit.body, format }, `kit.${format}`);
      if (answer.status === 200) {
        download(answer.name, answer.blob, answer.type);
        this.notify("", "kit");
      } else {
        this.notify(`Kit download failed: ${explain(answer)}`, "kit");
      }
    } catch (err) {
      this.notify(`Kit download failed: ${err.message}`, "kit");
    } finally {
      this.downloading -= 1;
    }
  }

  /** The bill of materials shown, as the kit's bom.json holds it. */
  downloadBill() {
    if (!this.kit) return;
    const { took_ms: _, ...bill } = this.kit.bom;
    const name = `mechanism-${this.kit.body.node_types.length}-joints-bom.json`;
    download(name, JSON.stringify(bill, null, 1), "application/json");
  }

  // -- for the browser tests ----------------------------------------------------------------

  /** Every part drawn (KitScene.parts: kind, name, layer or layers, position, a bar's ends),
   * in the kit's frame (mm, z up), at the current step and explode spacing; [] with no kit. */
  parts() {
    return this.kit && this.scene ? this.scene.parts() : [];
  }

  /** The last frame's draw calls and triangles (KitScene.drawn); null with no scene. */
  drawn() {
    return this.scene ? this.scene.drawn() : null;
  }
}
